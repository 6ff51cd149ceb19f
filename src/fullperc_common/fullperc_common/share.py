"""Where a package's installed data lives: ``share/<pkg>/<sub>``, else the source tree's copy.

Why one function: nodes, the evaluator and the simulator all load files shipped in a package's ``config/``
(layouts, ROMs, scene, task plans, parameter files). Installed (colcon, ``ros2 run``) they are under the
package's share directory from the ament index; run from a source checkout without ``install/`` they sit
next to the package's Python folder. Every such lookup goes through :func:`share_path`.
"""

from __future__ import annotations

from pathlib import Path

_SRC = Path(__file__).resolve().parents[2]  # src/ of a source checkout (or site-packages when installed)


def share_candidates(package: str, *parts: str) -> list[Path]:
    """Candidate paths of ``parts`` in ``package``'s data, installed share directory first."""
    cands: list[Path] = []
    try:
        from ament_index_python.packages import get_package_share_directory

        cands.append(Path(get_package_share_directory(package)).joinpath(*parts))
    except Exception:  # noqa: BLE001 - not installed / no ament index: the source tree only
        pass
    cands.append(_SRC.joinpath(package, *parts))
    return cands


def share_path(package: str, *parts: str) -> Path:
    """The first existing candidate of :func:`share_candidates`; FileNotFoundError naming every place tried."""
    cands = share_candidates(package, *parts)
    for p in cands:
        if p.exists():
            return p
    raise FileNotFoundError(f"{'/'.join(parts)} of {package} not found; looked in: "
                            + ", ".join(str(p) for p in cands))

"""Loading a vendor's C library through ctypes: the one loader every SDK backend uses.

NOKOV (``libnokov_sdk.so``) and Agile Robots (``libDianaApi.so``) are not shipped with fullperc; their path is a
node parameter. A wrong path, a file that is not a shared library, or a library without the expected symbols
must stop the node with one line naming the path and the parameter (the node's ``main`` treats the backend's
error type as fatal: exit 2), never with a ctypes traceback at the first call.
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Iterable, Mapping

Signature = tuple[list | None, object]  # (argtypes, restype)


def load_vendor_library(path: str, *, what: str, parameter: str, file_name: str,
                        signatures: Mapping[str, Signature], required: Iterable[str],
                        error: type[Exception] = RuntimeError) -> ctypes.CDLL:
    """Load ``path`` and declare ``signatures`` (symbol -> (argtypes, restype)) of the symbols it has.

    ``what`` names the library in messages (``NOKOV SDK``), ``parameter`` the node parameter that gives the path,
    ``file_name`` its usual file name. Every symbol in ``required`` must exist; the others are optional (newer
    or older SDKs) and the caller tests ``hasattr(lib, name)`` before using them. Errors raise ``error``.
    """
    if not path:
        raise error(f"parameter '{parameter}' is empty: give the path of {file_name}")
    if not os.path.isfile(path):
        raise error(f"{what} library not found: '{path}' does not exist (parameter '{parameter}')")
    try:
        lib = ctypes.CDLL(os.path.abspath(path))
    except OSError as e:
        raise error(f"cannot load {what} library '{path}': {e}") from e
    missing = [s for s in required if not hasattr(lib, s)]
    if missing:
        raise error(f"'{path}' is not the {what} library: missing symbols {', '.join(missing)}")
    for name, (argtypes, restype) in signatures.items():
        if hasattr(lib, name):
            fn = getattr(lib, name)
            fn.argtypes = argtypes
            fn.restype = restype
    return lib

"""The documentation: a short README as the front page, reference pages in docs/, links that resolve, and results
that are generated from the committed JSON, never typed in.

* README.md at most 300 lines, none over 200 characters; at least five pages in docs/;
* every relative link of README.md, CONTRIBUTING.md and docs/*.md points at a file that exists, and its ``#anchor``
  at a heading of that file (GitHub's heading slugs, duplicates numbered ``-1``, ``-2``);
* docs/results.md and the README's results block are exactly what ``scripts/results_page.py`` renders from
  bags/accuracy.json and bags/<profile>/eval.json, so a changed figure without a re-rendered page fails here;
* bags/accuracy.json was made with today's twin: its ``twin_hash`` per profile is what
  :func:`fullperc_eval.evaluation.accuracy.twin_hash` gives now (the scene configuration and plans file, hashed;
  nothing is simulated);
* no commit hashes or issue numbers in README.md or docs/: git log holds the history.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 300
README_MAX_WIDTH = 200
MIN_DOC_PAGES = 5
FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
LINK = re.compile(r"!?\[([^\]]*)\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
CODE_SPAN = re.compile(r"(`+)(.+?)\1")


def doc_files(root: Path = ROOT) -> list[Path]:
    return [root / "README.md", root / "CONTRIBUTING.md", *sorted((root / "docs").glob("*.md"))]


def prose_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line outside fenced code blocks."""
    out, fenced = [], False
    for i, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            out.append((i, line))
    return out


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: its text (links, code and HTML reduced to their text), lower case, every
    character but letters, digits, '_', '-' and spaces dropped, spaces turned into '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"<[^>]+>", "", text)
    text = CODE_SPAN.sub(lambda m: m.group(2), text)
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a Markdown file; a repeated slug gets -1, -2, ... as on GitHub."""
    seen: dict[str, int] = {}
    out = set()
    for _, line in prose_lines(path.read_text()):
        m = HEADING.match(line)
        if not m:
            continue
        s = slug(m.group(2))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out


def links(path: Path) -> list[tuple[int, str]]:
    """(line, target) of every Markdown link and image outside code (fenced blocks and code spans)."""
    out = []
    for i, line in prose_lines(path.read_text()):
        for m in LINK.finditer(CODE_SPAN.sub("", line)):
            out.append((i, m.group(2)))
    return out


def broken_links(files: list[Path], root: Path = ROOT) -> list[str]:
    """``file:line: target (why)`` for every relative link whose file does not exist or whose #anchor is not a
    heading of its target; links with a scheme (https:, mailto:) are not checked."""
    bad, cache = [], {}
    for f in files:
        for line, target in links(f):
            if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):
                continue
            path, _, anchor = target.partition("#")
            dest = (f.parent / path).resolve() if path else f.resolve()
            where = f"{f.relative_to(root)}:{line}: {target}"
            if not dest.is_relative_to(root.resolve()):
                bad.append(f"{where} (outside the repository)")
            elif not dest.exists():
                bad.append(f"{where} (no such file)")
            elif anchor and dest.suffix == ".md":
                if dest not in cache:
                    cache[dest] = anchors(dest)
                if anchor not in cache[dest]:
                    bad.append(f"{where} (no heading with anchor #{anchor} in {dest.name})")
    return bad


# ------------------------------------------------------------------------------------------- the checker
def test_slugs_are_githubs():
    assert slug("Accuracy over ten seeds (`make accuracy SEEDS=0-9 PROFILE=both`)") == \
        "accuracy-over-ten-seeds-make-accuracy-seeds0-9-profileboth"
    assert slug("Many targets: two `fusion_node` processes") == "many-targets-two-fusion_node-processes"
    assert slug("The link's covariance and the bridge link") == "the-links-covariance-and-the-bridge-link"
    assert slug("Health: what `/diagnostics` says and when") == "health-what-diagnostics-says-and-when"
    assert slug("Where a hop goes (`fullperc.hop_into`)") == "where-a-hop-goes-fullperchop_into"
    assert slug("See [the filter](x.md) ≤ 20 µs") == "see-the-filter--20-µs"


def test_the_link_checker_finds_planted_broken_links(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "b.md").write_text("# Title\n\n## Part one\n\n## Part one\n\n```\n# not a heading\n```\n")
    a = tmp_path / "a.md"
    a.write_text("# A\n"
                 "[ok](docs/b.md) [ok](docs/b.md#part-one) [ok](docs/b.md#part-one-1) [ok](#a) [web](https://x.org/y)\n"
                 "[gone](docs/c.md) [bad anchor](docs/b.md#not-a-heading) [third](docs/b.md#part-one-2)\n"
                 "`[in code](nowhere.md)`\n```\n[in a block](nowhere.md)\n```\n"
                 "![img](docs/missing.png) [up](../x.md)\n")
    found = broken_links([a], tmp_path)
    assert [f.split(": ", 1)[1] for f in found] == [
        "docs/c.md (no such file)", "docs/b.md#not-a-heading (no heading with anchor #not-a-heading in b.md)",
        "docs/b.md#part-one-2 (no heading with anchor #part-one-2 in b.md)", "docs/missing.png (no such file)",
        "../x.md (outside the repository)"], found


# ---------------------------------------------------------------------------------------- the real files
def test_the_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines (at most {README_MAX_LINES}): " \
                                           "move reference material to docs/"
    wide = [f"README.md:{i}: {len(s)} characters" for i, s in enumerate(lines, 1) if len(s) > README_MAX_WIDTH]
    assert not wide, f"lines over {README_MAX_WIDTH} characters:\n  " + "\n  ".join(wide)


def test_the_reference_lives_in_docs():
    pages = sorted(p.name for p in (ROOT / "docs").glob("*.md"))
    assert len(pages) >= MIN_DOC_PAGES, pages


def test_every_relative_link_resolves():
    bad = broken_links(doc_files())
    assert not bad, "broken links:\n  " + "\n  ".join(bad)


def test_no_commit_hashes_or_issue_numbers_in_the_docs():
    """History (which commit, which issue) belongs to git log, not to the reference."""
    hexes = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
    issues = re.compile(r"\bissues?[ -]?#?\d+", re.IGNORECASE)
    found = []
    for f in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for i, line in enumerate(f.read_text().splitlines(), 1):
            found += [f"{f.relative_to(ROOT)}:{i}: {m.group(0)}" for rx in (hexes, issues) for m in rx.finditer(line)]
    assert not found, "commit hashes or issue numbers:\n  " + "\n  ".join(found)


# ------------------------------------------------------------------------------------ generated results
def test_the_results_are_what_the_script_renders(load_script):
    mod = load_script("results_page")
    for path, text in mod.outputs(ROOT).items():
        assert path.read_text() == text, \
            f"{path.relative_to(ROOT)} is stale against the committed JSON: run python scripts/results_page.py"


def test_the_check_fails_on_a_figure_the_page_does_not_show(load_script, tmp_path, capsys):
    mod = load_script("results_page")
    for rel in ("README.md", "docs/results.md", "bags/accuracy.json", "bags/paper/eval.json", "bags/spec/eval.json"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / rel, tmp_path / rel)
    assert mod.main(["--check", "--root", str(tmp_path)]) == 0
    acc = json.loads((tmp_path / "bags/accuracy.json").read_text())
    profile = acc["profiles"][0]
    acc["summary"][profile]["table1_mae_mm"]["G-B-P"]["cbkf"][0] += 1.0   # a new run of make accuracy
    (tmp_path / "bags/accuracy.json").write_text(json.dumps(acc))
    capsys.readouterr()
    assert mod.main(["--check", "--root", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "docs/results.md" in err and "README.md" in err and "python scripts/results_page.py" in err, err
    assert mod.main(["--root", str(tmp_path)]) == 0            # re-rendered ...
    assert mod.main(["--check", "--root", str(tmp_path)]) == 0  # ... and current again


def test_the_committed_accuracy_run_is_of_todays_twin():
    from fullperc_eval.evaluation.accuracy import twin_hash

    acc = json.loads((ROOT / "bags" / "accuracy.json").read_text())
    assert acc["profiles"], "bags/accuracy.json names no profile"
    for profile in acc["profiles"]:
        assert acc["twin_hash"][profile] == twin_hash(profile), \
            f"bags/accuracy.json's {profile} bags are of another twin than today's: run make accuracy " \
            "(and python scripts/results_page.py)"

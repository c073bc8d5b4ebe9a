"""The library says what the software does, not how it came to be.

Issue numbers, work sessions ("the twenty-eighth session") and "the default since <date>" belong to the record of
how threedq was developed: the study pages (``docs/studies/``), the measurements with machine and date
(``docs/benchmarks.md``, ``docs/results.md``, ``docs/results/``, ``benchmarks/results/``) and the git history. This
test scans the rest of the tracked text: the Python sources outside ``tests/``, the packaged configs, the README, the
Dockerfile and the documentation pages, and fails with ``file:line`` for each hit.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path, PurePosixPath

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: these tests read the source tree; the Docker image holds the installed package and the tests only
needs_sources = pytest.mark.skipif(
    not (ROOT / "threedq" / "__init__.py").is_file(),
    reason="reads the source tree, which this install does not hold (e.g. the Docker image)")

#: folders whose Python files are scanned (setup.py too)
PY_FOLDERS = ("threedq", "stages", "datamodules", "benchmarks", "scripts")
#: documentation pages that record measurements with machine and date, or history: not scanned
DOCS_EXEMPT = ("docs/benchmarks.md", "docs/results.md")
#: folders never walked when git cannot list the files: anywhere, and at the top (run outputs, datasets, builds)
SKIP_DIRS = {".git", ".venv", "venv", "node_modules", "__pycache__", ".eggs", ".pytest_cache", ".mypy_cache",
             ".ruff_cache"}
SKIP_TOP_DIRS = {"runs", "data", "build", "dist", "shared"}

_ORDINAL_UNITS = "first|second|third|fourth|fifth|sixth|seventh|eighth|ninth"
_ORDINAL_TENS = "twenty|thirty|forty|fifty|sixty|seventy|eighty|ninety"
_DATE = r"\d{4}-\d{2}(?:-\d{2})?"

#: name -> pattern; each hit is a word about how the project was developed
PATTERNS: dict[str, re.Pattern[str]] = {
    # "issue 14", "issue #30", "issues #30 and #63", "(issue 14)"
    "issue reference": re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE),
    # "#63" after a space or an opening parenthesis (or at the start of a line): not a colour (#1f77b4, #123456),
    # not a markdown anchor (](#63-...) or page.md#63), not a heading (## 10 ...), not array[#...]; after "issue" the
    # reference above has it
    "issue number": re.compile(r"(?:^|(?<=[\s(]))(?<!\]\()(?<![Ii]ssue )(?<![Ii]ssues )#\d{2,3}\b(?![-\w])"),
    # a work session: "session", "sessions", "this session's"
    "session": re.compile(r"\bsessions?\b", re.IGNORECASE),
    # "twenty-eighth", "the thirtieth's" (compound and tens ordinals number sessions here), not a fraction ("a
    # twentieth of the bytes")
    "ordinal": re.compile(rf"(?<!\ba )(?<!\ban )(?<!\bone )\b(?:(?:{_ORDINAL_TENS})[- ](?:{_ORDINAL_UNITS})"
                          r"|twentieth|thirtieth|fortieth|fiftieth)\b", re.IGNORECASE),
    # "the default since 2026-12-05", "default since a14a6e0", "the default since the fifth ..."
    "default since": re.compile(
        rf"\bdefault\s+since\s+(?:{_DATE}|[0-9a-f]{{7,40}}\b|commit\b|issue\b|the\s+\S+\s+session\b)"
        r"|\bthe\s+default\s+since\b(?!\s+(?:it|they|this|that)\b)", re.IGNORECASE),
}


def hits_in_line(line: str) -> list[str]:
    """The process words of one line, as ``"<kind>: <matched text>"``."""
    return [f"{kind}: {m.group(0)!r}" for kind, pattern in PATTERNS.items() for m in pattern.finditer(line)]


def _listed_files() -> list[str] | None:
    """Tracked and untracked-but-not-ignored files, repository-relative and '/'-separated; None without git."""
    try:
        out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=ROOT,
                             capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return sorted({p for p in out.decode("utf-8", "replace").split("\0") if p})


def _walked_files() -> list[str]:
    out: list[str] = []
    for folder, dirs, files in os.walk(ROOT):
        top = Path(folder) == ROOT
        dirs[:] = [d for d in dirs if d not in SKIP_DIRS and not d.endswith(".egg-info")
                   and not (top and d in SKIP_TOP_DIRS)]
        for f in files:
            out.append((Path(folder) / f).relative_to(ROOT).as_posix())
    return sorted(out)


def scanned(path: str) -> bool:
    """Whether ``path`` (repository-relative, '/'-separated) is held to the rule."""
    p = PurePosixPath(path)
    top = p.parts[0]
    if p.suffix == ".py":
        return path == "setup.py" or (top in PY_FOLDERS and len(p.parts) > 1)
    if top == "configs" and p.suffix in (".yaml", ".yml"):
        return True
    if path in ("README.md", "Dockerfile"):
        return True
    return top == "docs" and len(p.parts) == 2 and p.suffix == ".md" and path not in DOCS_EXEMPT


def files_to_scan() -> list[str]:
    listed = _listed_files()
    paths = listed if listed is not None else _walked_files()
    return [p for p in paths if scanned(p) and (ROOT / p).is_file()]


@needs_sources
def test_no_process_words() -> None:
    files = files_to_scan()
    assert any(f.startswith("threedq/") for f in files), "found none of threedq's sources to scan"
    found: list[str] = []
    for path in files:
        text = (ROOT / path).read_text(encoding="utf-8", errors="replace")
        for number, line in enumerate(text.splitlines(), start=1):
            found += [f"{path}:{number}: {hit}" for hit in hits_in_line(line)]
    assert not found, ("words about how the project was developed (they belong in docs/studies/, docs/benchmarks.md, "
                       f"docs/results.md or the git history), {len(found)} hits:\n" + "\n".join(found))


@pytest.mark.parametrize("line, kinds", [
    # flagged
    ("since the twenty-eighth session (issue #63) the pairs", {"issue reference", "session", "ordinal"}),
    ("positives: occupancy (issue 14)", {"issue reference"}),
    ("ours + a second view set (issue #30; off in the main job)", {"issue reference"}),
    ("review mend for #63: names", {"issue number"}),
    ("the weighting (#63) stays", {"issue number"}),
    ("#63: GT boxes on the shape-only data", {"issue number"}),
    ("beside other sessions' runs", {"session"}),
    ("the Session's numbers", {"session"}),
    ("the twenty-ninth's measured arm", {"ordinal"}),
    ("as the thirtieth measured", {"ordinal"}),
    ("`round_lr: harmonic` (the default since 2026-11-29)", {"default since"}),
    ("`retrieval_occupancy_floor: 0.2`, the default since a14a6e0", {"default since"}),
    ("The default since the refresh was rewritten", {"default since"}),
    # not flagged
    ("color: '#1f77b4'  # matplotlib's first colour", set()),
    ("fill = #123456 in the legend", set()),
    ("palette #ffaa00 and #fff", set()),
    ("x = crops[#objects] is not python", set()),
    ("## 10 steps, a markdown heading", set()),
    ("[the section](usage.md#your-own-data-adapting-the-detector-without-labels)", set()),
    ("[anchor](#63-steps) and [x](page.md#10)", set()),
    ("`fast` is the default since it costs a quarter of `exact`", set()),
    ("a fifth of the objects; the second view; the 21st voxel", set()),
    ("kept in about a twentieth of the bytes, one twenty-fifth of the time", set()),
    ("issues a warning; an issue with 3D boxes", set()),
    ("the default is 0.5 (sessionless, obsessions aside)", set()),
])
def test_patterns(line: str, kinds: set[str]) -> None:
    assert {h.split(":", 1)[0] for h in hits_in_line(line)} == kinds


def test_scanned_selection() -> None:
    for path in ("threedq/pipeline/em.py", "stages/mining.py", "datamodules/scene_folder.py",
                 "benchmarks/em_seeds.py", "scripts/tool.py", "setup.py", "configs/stages/mining.yaml",
                 "configs/data/shapes.yaml", "README.md", "Dockerfile", "docs/usage.md", "docs/fidelity.md"):
        assert scanned(path), path
    for path in ("tests/test_em.py", "docs/studies/mined-pairs.md", "docs/benchmarks.md", "docs/results.md",
                 "docs/results/run.json", "benchmarks/results/x/README.md", "threedq.py", "configs/README.md"):
        assert not scanned(path), path

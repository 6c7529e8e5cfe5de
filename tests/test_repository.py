"""What a clone of the repository holds stands on its own: committed results, benchmarks and docs
name no folder of the machine that made them, and every citation of the model's specification
(SPEC §n: docs/model.md), of the style rules (docs/style.md rule n) and of a file of the
repository resolves inside it."""

from __future__ import annotations

import re
import subprocess
import tempfile
from pathlib import Path

from uavlae.factories import REPO_ROOT
from uavlae.files import ABSOLUTE_PATH, portable

RECORDS = (".json", ".md", ".csv", ".yaml", ".txt")


def tracked(*folders: str) -> list[Path]:
    """The files of ``folders`` a clone holds (git's list; every file where there is no git)."""
    res = subprocess.run(["git", "ls-files", "-z", *folders], cwd=REPO_ROOT, capture_output=True, text=True)
    if res.returncode == 0 and res.stdout:
        return [REPO_ROOT / f for f in res.stdout.split("\0") if f]
    return [p for d in folders for p in (REPO_ROOT / d).rglob("*") if p.is_file()]


def text_of(path: Path) -> str | None:
    try:
        return path.read_text(encoding="utf-8")
    except (UnicodeDecodeError, OSError):
        return None  # a figure, a tensor file


def test_no_committed_record_names_a_folder_of_the_machine_that_made_it():
    files = tracked("results", "benchmarks", "docs")
    assert len(files) > 100  # the records of three profiles are among them
    here = [str(REPO_ROOT.parent) + "/", str(Path(tempfile.gettempdir()).resolve()) + "/"]
    found = []
    for f in files:
        text = text_of(f)
        if text is None:
            continue
        rel = f.relative_to(REPO_ROOT)
        found += [f"{rel}: {h}" for h in here if h in text]
        if f.suffix in RECORDS:  # data, not code: any absolute path is some machine's folder
            found += [f"{rel}: {m}" for m in ABSOLUTE_PATH.findall(text)]
    assert found == []


def test_portable_paths_by_hand(tmp_path):
    # a checkout and its sibling (folders need not exist to be named)
    assert portable("python b.py --base /srv/x/base --out /srv/x/checkout/benchmarks/x.json", "/srv/x/checkout") == (
        "python b.py --base ../base --out benchmarks/x.json")
    assert portable("/srv/x/checkout", "/srv/x/checkout") == "."
    assert portable("url=http://127.0.0.1:8080/v1 a/b ~/.cache/f", "/srv/x/checkout") == (
        "url=http://127.0.0.1:8080/v1 a/b ~/.cache/f")  # no absolute path in it
    # the temporary folder, unless the checkout itself lies in it
    tmp = Path(tempfile.gettempdir()).resolve()
    assert portable(f"run_dir={tmp / 'ttt' / 'run'}", "/srv/x/checkout") == "run_dir=<tmp>/ttt/run"
    assert portable(f"--set {tmp_path / 'c' / 'results' / 's.json'}", tmp_path / "c") == "--set results/s.json"


# "SPEC §8", "SPEC §2-§7", "SPEC §8–§9", "docs/model.md §7-§8", "SPEC §10's"
SPEC_CITATION = re.compile(r"(?:\bSPEC|docs/model\.md)(?:'s)?\s+((?:§\s*\d+\s*(?:[-–,]|and|or)?\s*)+)")
RULE_CITATION = re.compile(r"docs/style\.md,? rules?\s+(\d+)")
# a cited file of the code, configs, docs or benchmarks (results/ is written by runs: a study may
# cite the files its runs will write there)
FILE_CITATION = re.compile(r"(?<![\w/.-])((?:docs|uavlae|benchmarks|tests|experiments|conf)/[\w/.-]*\w\.(?:md|py|yaml|json|png|pt))")


def test_every_citation_resolves_inside_the_repository():
    model = (REPO_ROOT / "docs" / "model.md").read_text()
    sections = {int(n) for n in re.findall(r"^## (\d+)\. ", model, re.MULTILINE)}
    assert sections == set(range(1, 11))
    assert "SPEC §n" in model and "*SPEC's world*" in model  # the page says what the short forms mean
    rules = {int(n) for n in re.findall(r"^(\d+)\. ", (REPO_ROOT / "docs" / "style.md").read_text(), re.MULTILINE)}
    assert rules == set(range(1, 14))
    this = Path(__file__).resolve()
    cited, broken = 0, []
    for f in tracked("."):
        if f.suffix not in (".py", ".md", ".yaml", ".txt") and f.name != "Makefile":
            continue
        text = text_of(f)
        if text is None or f.relative_to(REPO_ROOT).parts[0] == "results":
            continue
        rel = f.relative_to(REPO_ROOT)
        # the specification and the style rules are cited from here, no longer from outside
        broken += [f"{rel}: {name}" for name in ("SPEC.md", "STYLE.md") if name in text and f.resolve() != this]
        for m in SPEC_CITATION.finditer(text):
            cited += 1
            broken += [f"{rel}: {m.group(0).strip()}" for n in re.findall(r"\d+", m.group(1)) if int(n) not in sections]
        for m in RULE_CITATION.finditer(text):
            cited += 1
            broken += [f"{rel}: {m.group(0)}"] if int(m.group(1)) not in rules else []
        if f.resolve() != this:  # this file's own examples are not citations
            # from inside the package, "conf/..." and "experiments/..." are the package's own folders
            bases = (REPO_ROOT, REPO_ROOT / "uavlae") if rel.parts[0] == "uavlae" else (REPO_ROOT,)
            broken += [f"{rel}: {m.group(1)}" for m in FILE_CITATION.finditer(text)
                       if not any((b / m.group(1)).exists() for b in bases)]
    assert cited > 90  # the code cites the specification throughout
    assert broken == []

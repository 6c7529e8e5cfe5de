"""What a clone of the repository holds stands on its own: committed results, benchmarks and docs
name no folder of the machine that made them."""

from __future__ import annotations

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

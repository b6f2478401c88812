"""The user pages speak of the product only: no developers' history or placeholders, no dead links, and
docs/RESULTS.md's tables as experiments/results_tables.py prints them. Fast: no Ray, no torch.

User pages: README.md, every docs/*.md at the top of docs/ (not the lab notebook, docs/lab/),
configs/README.md and cluster/README.md.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
USER_PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md"), ROOT / "configs" / "README.md",
                     ROOT / "cluster" / "README.md"])
PAGE_IDS = [str(p.relative_to(ROOT)) for p in USER_PAGES]

# What a user page may not say: the developers' working history, their machine and tools, placeholders.
FORBIDDEN = {
    "the word session(s)": re.compile(r"\bsessions?\b", re.IGNORECASE),
    "an issue number": re.compile(r"\bissues?\s*(#\s*\d*|\d+)", re.IGNORECASE),
    "'this machine'": re.compile(r"\bthis machine\b", re.IGNORECASE),
    "'the device'": re.compile(r"\bthe device\b", re.IGNORECASE),
    "MAKERUN": re.compile(r"MAKERUN"),
    "TODO": re.compile(r"\bTODO\b"),
    "XXX": re.compile(r"XXX"),
    "shared/spec": re.compile(r"shared/spec"),
}
# outside code: a placeholder left in prose (code may name a template such as `setting<K>_planner.gif`)
PLACEHOLDER = re.compile(r"<[A-Z][A-Z0-9_ -]*>")
MAX_LINES = {"docs/RESULTS.md": 300, "README.md": 150}

FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`]+`")  # may run over a line break
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def prose(text: str) -> str:
    """``text`` with its code (fenced blocks, inline spans) blanked out, every character at its place."""
    def blank(m: re.Match) -> str:
        return re.sub(r"[^\n]", " ", m.group(0))

    return INLINE_CODE.sub(blank, FENCE.sub(blank, text))


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text(encoding="utf-8"))
    found: set[str] = set()
    for line in text.splitlines():
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            base, n = slug(m.group(1)), 1
            name = base
            while name in found:  # GitHub numbers repeated headings
                name, n = f"{base}-{n}", n + 1
            found.add(name)
    return found


@pytest.mark.parametrize("page", USER_PAGES, ids=PAGE_IDS)
def test_a_user_page_has_no_developer_history_or_placeholders(page: Path):
    text = page.read_text(encoding="utf-8")
    lines = text.splitlines()
    found = [(m.start(), what, m.group(0)) for what, pattern in FORBIDDEN.items() for m in pattern.finditer(text)]
    found += [(m.start(), "a placeholder <IN CAPITALS>", m.group(0)) for m in PLACEHOLDER.finditer(prose(text))]
    bad = []
    for start, what, match in sorted(found):
        number = text.count("\n", 0, start) + 1
        bad.append(f"{page.relative_to(ROOT)}:{number}: {what} ({match!r}): {lines[number - 1].strip()[:160]}")
    assert not bad, "user pages speak of the product only:\n" + "\n".join(bad)


@pytest.mark.parametrize("page", USER_PAGES, ids=PAGE_IDS)
def test_a_user_page_links_only_to_files_that_exist(page: Path):
    bad = []
    for m in LINK.finditer(prose(page.read_text(encoding="utf-8"))):
        target = m.group(1)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, https:, mailto:, ...
            continue
        path, _, fragment = target.partition("#")
        file = page if not path else (page.parent / path).resolve()
        if not file.exists():
            bad.append(f"{page.relative_to(ROOT)}: [{target}]: no file {path}")
        elif fragment and file.suffix == ".md" and fragment not in anchors(file):
            bad.append(f"{page.relative_to(ROOT)}: [{target}]: no heading #{fragment} in {file.relative_to(ROOT)}")
    assert not bad, "dead links:\n" + "\n".join(bad)


@pytest.mark.parametrize("name", sorted(MAX_LINES))
def test_a_page_stays_short(name: str):
    lines = len((ROOT / name).read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_LINES[name], f"{name} has {lines} lines; at most {MAX_LINES[name]}"


@pytest.mark.parametrize("script, page", [("experiments/results_tables.py", "docs/RESULTS.md"),
                                          ("experiments/results_tables.py --recipe", "docs/RECIPE.md"),
                                          ("experiments/scaling_model.py", "docs/SCALING.md")])
def test_a_pages_tables_are_those_its_script_prints(script: str, page: str):
    """Each block a script prints (from docs/results/*.json) stands verbatim in its page."""
    printed = subprocess.run([sys.executable, *script.split()], cwd=ROOT, capture_output=True, text=True,
                             timeout=120, check=True).stdout
    tables = [block.strip() for block in re.split(r"\n\s*\n", printed) if block.strip()]
    assert tables, f"{script} printed nothing"
    text = (ROOT / page).read_text(encoding="utf-8")
    missing = [table.splitlines()[0] for table in tables if table not in text]
    assert not missing, f"{page} lacks these blocks as {script} prints them (rerun it and paste): " + "; ".join(missing)


def test_the_readmes_settings_table_is_the_one_results_tables_py_prints():
    """README.md's figures come from docs/results/*.json too (`experiments/results_tables.py --readme`)."""
    printed = subprocess.run([sys.executable, "experiments/results_tables.py", "--readme"], cwd=ROOT,
                             capture_output=True, text=True, timeout=120, check=True).stdout.strip()
    assert printed.count("\n") == 5, printed  # a header, its rule and the four settings
    assert printed in (ROOT / "README.md").read_text(encoding="utf-8"), (
        "README.md lacks the settings table as `experiments/results_tables.py --readme` prints it (rerun it and paste)")


def test_results_tables_refuses_reports_of_another_team_beside_each_other():
    """A table that sets reports side by side (test beside validation, a changed game beside its own) stops on
    a report of another team: a page cannot mix an old team's figures with a new one's."""
    sys.path.insert(0, str(ROOT / "experiments"))
    try:
        import results_tables
    finally:
        sys.path.remove(str(ROOT / "experiments"))
    mine = {"env_steps": 480768, "trained": {"wall_seconds": 3957.6}}
    same = {"env_steps": 480768, "trained": {"wall_seconds": 3957.6}, "success": 0.9}
    older = {"env_steps": 480768, "trained": {"wall_seconds": 6156.0}}
    assert results_tables.same_team(mine, same, "same.json")["success"] == 0.9
    with pytest.raises(SystemExit, match="older.json: not the team"):
        results_tables.same_team(mine, older, "older.json")

"""Every relative link in the Markdown docs points at a file that exists and, with ``#``, a heading in it."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted(
    [*ROOT.glob("*.md"), *(ROOT / "docs").glob("*.md"), ROOT / "benchmarks" / "README.md"],
    key=str,
)


def github_anchors(page: Path) -> set[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # a "# comment" in code is no heading
    anchors = set()
    for heading in re.findall(r"^#+ (.+)$", text, flags=re.M):
        anchors.add(re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-"))
    return anchors


def broken_links(page: Path) -> list[str]:
    """The relative links of ``page`` whose file or heading does not exist."""
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    broken = []
    for link in re.findall(r"\]\(([^)\s]+)\)", text):
        if link.startswith(("http://", "https://", "mailto:")):
            continue
        path, _, anchor = link.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            broken.append(f"{link} (no such file)")
        elif anchor and target.suffix == ".md" and anchor not in github_anchors(target):
            broken.append(f"{link} (no such heading)")
    return broken


def test_the_rules_on_a_hand_case(tmp_path):
    page = tmp_path / "p.md"
    page.write_text(
        "# Title\n\n## Rollout (`benchmarks/rollout.py`)\n\n## Runs (recorded 2026-11-29/30, v1)\n\n"
        "[a](#runs-recorded-2026-11-2930-v1) [b](p.md#title) [c](#runs-recorded-2026-112930-v1) "
        "[d](q.md) [e](https://example.org/x.md)\n```\n# not a heading\n[f](nowhere.md)\n```\n"
    )
    assert github_anchors(page) == {"title", "rollout-benchmarksrolloutpy", "runs-recorded-2026-11-2930-v1"}
    assert broken_links(page) == ["#runs-recorded-2026-112930-v1 (no such heading)", "q.md (no such file)"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    broken = broken_links(page)
    assert not broken, f"{page.relative_to(ROOT)}: " + ", ".join(broken)

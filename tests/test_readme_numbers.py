"""Every result figure in the README comes from a generated block: a percentage, a speed-up or a millisecond
figure outside the ``<!-- name:begin/end -->`` blocks fails this test (the interval level ``95 %`` and the control
period ``25 ms`` are settings, not results). The reproduction's headline block is what ``egcbf reproduce
--report-only`` writes from the committed cells."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"<!-- ([\w-]+):begin -->.*?<!-- \1:end -->", re.DOTALL)
RESULT = re.compile(
    r"(?<![\w.])(?:\d+(?:\.\d+)?\s?%"  # a percentage
    r"|\d+(?:\.\d+)?(?:\s?-\s?\d+(?:\.\d+)?)?\s?x\b"  # a speed-up: 25x, 25-120x
    r"|\d+(?:\.\d+)?\s?ms\b)"  # a time in milliseconds
)
SETTINGS = {"95 %", "25 ms"}


def result_figures(text: str) -> list[str]:
    """The result figures of ``text`` outside its generated blocks, with their line."""
    outside = BLOCK.sub("", text)
    found = []
    for line in outside.splitlines():
        for m in RESULT.finditer(line):
            if m.group(0) not in SETTINGS:
                found.append(f"{m.group(0)!r} in: {line.strip()[:100]}")
    return found


@pytest.mark.parametrize("page", ["README.md", "docs/index.md"])
def test_no_result_figure_outside_a_generated_block(page):
    figures = result_figures((ROOT / page).read_text())
    assert not figures, f"{page}: result figures outside generated blocks:\n" + "\n".join(figures)


def test_the_checker_finds_figures_and_skips_blocks():
    text = (
        "EGCBF+ is 97.2 % safe, 25-120x faster, 0.3 ms a step; 95 % intervals\n<!-- a:begin -->\n99 %\n<!-- a:end -->"
    )
    assert [f.split(" in:")[0] for f in result_figures(text)] == ["'97.2 %'", "'25-120x'", "'0.3 ms'"]
    assert result_figures("SE(2)x R, 3x3 matrices are no speed-up? 3x") == [
        "'3x' in: SE(2)x R, 3x3 matrices are no speed-up? 3x"
    ]


def test_the_readme_headline_is_generated_from_the_committed_cells():
    from egcbf import reproduce as rp
    from egcbf.reproduce import SweepConfig
    from egcbf.reproduce.headline import headline_markdown

    out = ROOT / "docs" / "results" / "reproduction"
    if not any(out.rglob("N*.json")):
        pytest.skip("no committed reproduction cells")
    cfg = SweepConfig(out=out)
    body = headline_markdown(cfg, rp.load_cells(cfg))
    readme = (ROOT / "README.md").read_text()
    block = readme.split("<!-- reproduction-headline:begin -->", 1)[1].split("<!-- reproduction-headline:end -->")[0]
    assert body in block

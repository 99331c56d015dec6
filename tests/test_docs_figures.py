"""Figures the README and the docs quote from a committed benchmark result are printed in that result.

A paragraph quotes a result when it names ``benchmarks/results/NAME.md`` (or ``.json`` or
``.{json,md}``), or when it carries an HTML comment ``<!-- figures: NAME, NAME -->`` (invisible in
the rendered page; for a paragraph that states a result's figures without naming its file). Every
decimal figure and every percentage in a quoting paragraph's prose (not in code) must be printed in the result's
Markdown: as written, or as the rounding of a number printed there with more decimals. Figures
the Markdown deliberately does not print (an earlier measurement, a ratio worked out in the text,
a number only in the result's JSON) are listed in the paragraph's ``<!-- unchecked: 3.3, 1.08 -->``
comment, so that each exception is visible where it is made.

This is a net, not a proof: a result prints hundreds of numbers, so a stale figure passes when the
same digits happen to be printed elsewhere in it: moving each quoted figure by one in its last digit,
135 of 300 still passed on the results of 2026-11-25. A paragraph with several stale figures is caught.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]

CITATION = re.compile(r"benchmarks/results/([A-Za-z0-9_]+)\.(?:md|json|\{json,md\})")
QUOTES = re.compile(r"<!--\s*figures:\s*([^>]*?)\s*-->")
UNCHECKED = re.compile(r"<!--\s*unchecked:\s*([^>]*?)\s*-->")
#: A figure in prose: a decimal (digits, a point, digits) or a whole number, with its percent sign
#: if it has one; decimals and percentages are checked, not part of a version, a path or a longer token.
FIGURE = re.compile(r"(?<![\w./\-])(\d[\d,]*(?:\.\d+)?)(?![\w.]|\.\d)( ?%)?")
#: A number as a result prints it, with its percent sign if it has one.
PRINTED = re.compile(r"(?<![\w.])(\d[\d,]*(?:\.\d+)?)( ?%)?")
CODE = re.compile(r"```.*?```|`[^`\n]*`", flags=re.S)
COMMENT = re.compile(r"<!--.*?-->", flags=re.S)


def _list(text: str) -> list[str]:
    return [item.strip() for item in text.split(",") if item.strip()]


def quoted_results(paragraph: str) -> set[str]:
    """The names of the results a paragraph quotes."""
    names = set(CITATION.findall(paragraph))
    for marker in QUOTES.findall(CODE.sub(" ", paragraph)):  # a comment shown as code is an example
        names.update(_list(marker))
    return names


def figures(paragraph: str) -> list[str]:
    """The figures of a paragraph's prose (``"2.27"``, ``"12%"``), less those its ``unchecked`` comment lists."""
    prose = CODE.sub(" ", paragraph)
    exempt = {f.replace(" ", "") for marker in UNCHECKED.findall(prose) for f in _list(marker)}
    prose = COMMENT.sub(" ", prose)
    prose = re.sub(r"\]\([^)]*\)", "]", prose)  # link targets
    found = [number + ("%" if percent else "") for number, percent in FIGURE.findall(prose) if "." in number or percent]
    return [f for f in found if f not in exempt and f.rstrip("%") not in exempt]


def is_printed(figure: str, text: str) -> bool:
    """Whether ``text`` prints ``figure``, as written or as a number that rounds to it at its decimals.

    A whole-number percentage (``"12%"``) must be printed with its percent sign (whole numbers are
    everywhere in a result); a decimal one may be printed without (tables print the sign in the header).
    """
    number, percent = figure.rstrip("%"), figure.endswith("%")
    value, decimals = float(number.replace(",", "")), len(number.partition(".")[2])
    for printed, printed_percent in PRINTED.findall(text):
        if percent and not decimals and not printed_percent:
            continue
        printed_decimals = len(printed.partition(".")[2])
        if printed == number or (printed_decimals > decimals
                                 and round(float(printed.replace(",", "")), decimals) == value):
            return True
    return False


def quotations() -> list[tuple[str, int, str, set[str]]]:
    """(page, paragraph number from 1, paragraph, results) of every quoting paragraph."""
    found = []
    for page in PAGES:
        for number, paragraph in enumerate(re.split(r"\n\s*\n", page.read_text()), start=1):
            names = quoted_results(paragraph)
            if names:
                found.append((page.relative_to(REPO).as_posix(), number, paragraph, names))
    return found


QUOTATIONS = quotations()


def test_the_readme_and_the_numbers_pages_quote_results():
    pages = {page for page, *_ in QUOTATIONS}
    assert {"README.md", "docs/method.md", "docs/solvers.md", "docs/season.md"} <= pages


@pytest.mark.parametrize(("page", "number", "paragraph", "names"), QUOTATIONS,
                         ids=[f"{page}:{number}" for page, number, _, _ in QUOTATIONS])
def test_quoted_figures_are_printed_in_the_result(page, number, paragraph, names):
    texts = []
    for name in sorted(names):
        md = RESULTS / f"{name}.md"
        assert md.exists(), f"{page}, paragraph {number} quotes benchmarks/results/{name}.md, which does not exist"
        texts.append(md.read_text())
    missing = [f for f in figures(paragraph) if not is_printed(f, "\n".join(texts))]
    assert not missing, (
        f"{page}, paragraph {number} quotes benchmarks/results/{{{','.join(sorted(names))}}}.md, which do not "
        f"print {missing}: update the text from the result, or list figures it deliberately does not print in "
        f"<!-- unchecked: ... -->. The paragraph begins: {paragraph[:300]!r}")


def test_the_check_catches_a_moved_figure():
    text = "gate 3.2 % > 5 m (95 % CI 2.1-4.6), p95 2.27 m, rho 0.5949097, best 11.8 %, 13 events"
    assert is_printed("3.2", text) and is_printed("2.27", text) and is_printed("0.59", text)
    assert is_printed("3.2%", text) and is_printed("12%", text) and is_printed("2.27%", text)
    assert not is_printed("3.3", text) and not is_printed("2.2", text) and not is_printed("0.60", text)
    assert not is_printed("13%", text) and not is_printed("5%", text)
    assert figures("`x=1.5` and 2.5 m, 12 % of 40 events, v3.11, [a](b/1.2.md), was 3.3 % <!-- unchecked: 3.3 -->") == [
        "2.5", "12%"]
    assert quoted_results("<!-- figures: a, b --> and benchmarks/results/c.{json,md}") == {"a", "b", "c"}
    assert quoted_results("write `<!-- figures: a -->` to quote a") == set()

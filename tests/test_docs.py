"""The docs read whole: no paragraph of README.md or docs/*.md opens or ends mid-sentence,
and no measured figure stands in their prose that no bench and no ``docs/make_docs.py``
produced.

A paragraph is a run of non-blank lines outside code (fenced, or indented after a blank
line), generated blocks (``<!-- generated ... -->`` to ``<!-- end ... -->``), tables,
headings, list items, pictures and HTML comments. It ends a sentence: its last character
is ``.``, ``!``, ``?`` or ``:`` (a colon introduces the code, table or list that follows),
after which only closing marks (``)``, ``]``, ``*``, ``_``, a backtick, a quote) may
stand. It opens one: its first letter is not lower case, but where it goes on after a
code block (``... at file scope:`` / code / ``with X ...``) and where it opens with the
tool's own name, ``ecmgen``.

A figure is a decimal number of millivolts in prose (``55.9 mV``, each number of
``28.1 / 13.6 mV`` or ``10.6 → 3.7 mV``): the unit the accuracy claims are made in. It is
produced where it appears in a generated block of the docs (docs/make_docs.py writes them)
or in a committed bench baseline (bench/baseline/*.json, in mV to 0.1), or where its
paragraph, or the paragraph that opens its section, names the bench script that measures
it (``bench/NAME.py``, ``cd bench && python NAME.py`` or ``docs/make_docs.py``, which must
exist). A figure of another origin goes through
ALLOWED with the reason it may stand.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]

# (page, figure) -> why it may stand though no bench produces it
ALLOWED: dict[tuple[str, str], str] = {
    ("commands.md", "44.8"): "a committed model (tests/data/panasonic-temperature-model.json) "
                             "on the shared 25 degC US06: no fit of the code changes it",
    ("commands.md", "43.8"): "the same, the voltage moved one sample earlier",
    ("results.md", "0.5"): "a bound tests/test_codegen_temperature.py asserts (TOL)",
    **{("diagnose.md", f): "printed by `ecmgen diagnose` on the 25 degC example, the command "
                           "named beside it" for f in ("15.08", "6.47", "6.35")},
    **{("diagnose.md", f): "printed by `ecmgen diagnose` on the A123 example, which "
                           "tests/test_diagnose_real.py runs" for f in ("10.6", "3.7", "17.0",
                                                                        "13.4", "2.93", "3.91")},
}

_END = re.compile(r"[.!?:][)\]*_`\"']*$")
_FIGURES = re.compile(r"(\d+\.\d+(?:\s*(?:/|→|->|against|and|or|to|–)\s*\d+\.\d+)*)\s*mV\b")
_SOURCE = re.compile(r"(bench/[\w/]+\.py|docs/make_docs\.py)")
_CD_BENCH = re.compile(r"cd bench && python ([\w/]+\.py)")


def blocks(text: str) -> list[tuple[int, list[str], str]]:
    """(line number, lines, kind) of each block: kind "prose", "code", "generated",
    "table", "heading", "list", "other"."""
    out: list[tuple[int, list[str], str]] = []
    lines = text.split("\n")
    k = 0
    while k < len(lines):
        line = lines[k]
        if not line.strip():
            k += 1
            continue
        start = k
        if line.lstrip().startswith("```"):
            k += 1
            while k < len(lines) and not lines[k].lstrip().startswith("```"):
                k += 1
            out.append((start + 1, lines[start:k + 1], "code"))
            k += 1
            continue
        if line.startswith("<!-- generated"):
            while k < len(lines) and not lines[k].startswith("<!-- end"):
                k += 1
            out.append((start + 1, lines[start:k + 1], "generated"))
            k += 1
            continue
        while k < len(lines) and lines[k].strip() and not lines[k].lstrip().startswith("```"):
            k += 1
        para = lines[start:k]
        first = para[0]
        kind = ("code" if first.startswith("    ") else
                "table" if first.lstrip().startswith("|") else
                "heading" if first.startswith("#") else
                "list" if re.match(r"\s*([-*+]|\d+\.) ", first) else
                "other" if first.lstrip().startswith(("<!--", "![", ">")) else "prose")
        out.append((start + 1, para, kind))
    return out


def prose(page: Path):
    """(line, text, the kind of the block before, the first paragraph of its section) of
    each prose paragraph of ``page``; a section runs from a heading to the next."""
    found = blocks(page.read_text())
    opening = ""
    for n, (line, para, kind) in enumerate(found):
        text = " ".join(p.strip() for p in para)
        if kind == "heading":
            opening = None
        elif kind == "prose" and opening is None:
            opening = text
        if kind == "prose":
            yield line, text, found[n - 1][2] if n else "", opening or ""


def produced_figures() -> set[str]:
    """Every figure a generated block or a committed bench baseline holds."""
    text = " ".join(" ".join(para) for page in PAGES
                    for _, para, kind in blocks(page.read_text()) if kind == "generated")
    figures = set(re.findall(r"\d+\.\d+", text))
    for path in sorted((REPO / "bench" / "baseline").glob("*.json")):
        def walk(v):
            if isinstance(v, dict):
                for x in v.values():
                    walk(x)
            elif isinstance(v, float):
                figures.add(f"{v:.1f}")
        walk(json.loads(path.read_text()))
    return figures


def test_no_paragraph_opens_or_ends_mid_sentence():
    cut = []
    for page in PAGES:
        for line, text, before, _ in prose(page):
            where = f"{page.relative_to(REPO)}:{line}"
            if not _END.search(text):
                cut.append(f"{where}: ends mid-sentence: ...{text[-50:]!r}")
            if re.match(r"[a-z]", text) and before != "code" and not text.startswith("ecmgen"):
                cut.append(f"{where}: opens mid-sentence: {text[:50]!r}...")
    assert not cut, "\n".join(cut)


def test_every_figure_in_the_docs_comes_from_a_bench_or_make_docs():
    produced = produced_figures()
    stray = []
    for page in PAGES:
        for line, text, _, opening in prose(page):
            named = f"{text} {opening}"
            sources = [s for s in _SOURCE.findall(named) + [
                f"bench/{b}" for b in _CD_BENCH.findall(named)] if (REPO / s).is_file()]
            for run in _FIGURES.findall(text):
                for figure in re.findall(r"\d+\.\d+", run):
                    if figure in produced or sources or (page.name, figure) in ALLOWED:
                        continue
                    stray.append(f"{page.relative_to(REPO)}:{line}: {figure} mV")
    assert not stray, "figures no bench or docs/make_docs.py produced:\n" + "\n".join(stray)


@pytest.mark.parametrize("text, cut", [
    ("A sentence that stops at the", True), ("A whole sentence.", False),
    ("Ends on code: `x = 1`.", False), ("Introduces a list:", False),
    ("(A bracketed sentence.)", False), ("Ends on a link [here](x.md).", False),
])
def test_the_rule_on_examples(text, cut):
    assert (not _END.search(text)) == cut


def test_the_rule_sees_the_blocks():
    text = ("Prose that goes on\n\n```sh\nno end\n```\n\nwith a clause after the code.\n\n"
            "| a | b |\n|---|---|\n\n- a list item\n\n    indented code\n\n"
            "<!-- generated: x -->\n12.3 mV inside\n<!-- end: x -->\n")
    assert [k for _, _, k in blocks(text)] == ["prose", "code", "prose", "table", "list",
                                               "code", "generated"]
    assert _FIGURES.findall("MAE 28.1 / 13.6 mV, 10.6 → 3.7 mV") == ["28.1 / 13.6",
                                                                       "10.6 → 3.7"]


# --------------------------------------------------------------------------- numbers

def test_numbers_are_printed_as_a_person_writes_them():
    """JSON: 12 significant digits, no binary noise of summed time stamps (converge_s was
    23374.000000000004), null for a figure without a value; tables: "-" for it, never
    "nan" (the MAE above 10 % SOC of a run that never gets there)."""
    from types import SimpleNamespace

    import numpy as np

    from ecmgen.files import json_text
    from ecmgen.report import figure, validation_table

    assert json_text({"converge_s": 23374.000000000004, "x": 0.1 + 0.2,
                      "none": float("nan"), "small": 1.2345678901234e-7}) == (
        '{"converge_s": 23374.0, "x": 0.3, "none": null, "small": 1.23456789012e-07}')
    assert figure(float("nan"), "15.2f") == " " * 14 + "-" and figure(55.516, ".1f") == "55.5"
    metrics = SimpleNamespace(mae_v=0.4329, rmse_v=0.5, max_abs_v=0.7)
    run = SimpleNamespace(overall=metrics, soc_above_10=SimpleNamespace(mae_v=np.nan),
                          temperature_range_c=None)
    table = validation_table(SimpleNamespace(validations={"curve": {"s2.csv": run}},
                                             best="curve"))
    assert "nan" not in table and "432.90" in table

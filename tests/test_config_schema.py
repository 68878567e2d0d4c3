"""One schema for the config: every section and key known (typos refused, with the
nearest name, in every section), the loader's own lists and defaults equal to its rows,
and the README's config reference generated from it."""

from __future__ import annotations

import re
import textwrap
from dataclasses import fields

import pytest

from conftest import REPO
from ecmgen.cli import main
from ecmgen.config import C_ESTIMATORS, ESTIMATOR_FILTERS, EstimatorConfig, load_config
from ecmgen.config.schema import BY_NAME, SECTIONS, reference
from ecmgen.errors import InputError

HEAD = ('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "p.csv"\nocv = "p.csv"\n'
        'cycle = "p.csv"\n')


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "p.csv").write_text("time_s,current_a,voltage_v\n0,0,3.7\n1,0,3.7\n")
    return tmp_path


def load(folder, text):
    cfg = folder / "c.toml"
    cfg.write_text(text)
    return load_config(cfg)


# every section: a misspelt key, the name it should be, and the line that holds it
TYPOS = [
    ("[cell]\ncapacity_a = 2.9\n" + HEAD.split("\n", 2)[2], "capacity_ah"),
    (HEAD + "pulse_soc0 = 0.5\n", "pulses_soc0"),       # ran with the default start SOC
    (HEAD + "[dcir]\ntime_s = [0.1, 1, 3, 6]\n", "times_s"),
    (HEAD + "[fit]\nmethod = [\"lm\"]\n", "methods"),
    (HEAD + "[c]\nnumerc = \"float\"\n", "numeric"),        # gave both numerics
    (HEAD + "[c]\nestimater = \"ekf\"\n", "estimator"),     # dropped the estimator
    (HEAD + "[model]\nwarm_row = 40\n", "warm_row_c"),
    (HEAD + "[estimator]\nfiltre = \"ukf\"\n", "filter"),
    (HEAD + "[diagnose]\njudge_soc = 1.0\n", "judge_soc0"),
    (HEAD + "[data.columns]\ncurent = \"I\"\n", "current"),
    (HEAD + "[data.columns.cycle]\nvoltage_unt = \"mV\"\n", "voltage_unit"),
    (HEAD.replace('pulses = "p.csv"\n', "") + '[[data.pulse_tests]]\nfile = "p.csv"\n'
     'temperature = 25\n', "temperature_c"),
    (HEAD + "[estimater]\nfilter = \"ukf\"\n", "estimator"),
]


@pytest.mark.parametrize("text, near", TYPOS, ids=[t[1] for t in TYPOS])
def test_a_typo_is_refused_in_every_section_with_the_nearest_name(folder, capsys, text, near):
    """Before: typos in [cell], [data], [dcir], [fit], [c] and [diagnose] were ignored:
    `[c] numerc` built both numerics, `[c] estimater = "ekf"` no estimator,
    `[data] pulse_soc0 = 0.5` ran from the default start SOC, all exit 0."""
    with pytest.raises(InputError) as exc:
        load(folder, text)
    assert f"did you mean {near!r}" in str(exc.value) and "\n" not in str(exc.value)
    assert main(["build", str(folder / "c.toml"), "--out", str(folder / "out"), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"did you mean {near!r}" in err
    assert not (folder / "out").exists()


@pytest.mark.parametrize("text, words", [
    (HEAD + "[c]\ndt_s = -1\n", "c.dt_s must lie in"),
    (HEAD + "[c]\nnumeric = \"double\"\n", "c.numeric must be one of"),
    (HEAD + "[dcir]\nmin_rest_s = \"30 s\"\n", "dcir.min_rest_s must be a number"),
    (HEAD + "[estimator]\ncurrent_gain_error = 2.0\n", "estimator.current_gain_error"),
    (HEAD + "[estimator]\nstart = \"loaded\"\n", "estimator.start must be one of"),
    (HEAD + "[diagnose]\nsplit = 0.95\n", "diagnose.split must lie in"),
    (HEAD + "[data.columns]\ntime = 0\n", "data.columns.time must be a column name"),
    (HEAD + "[fit]\nseed = -1\n", "fit.seed must lie in"),
])
def test_values_are_checked_against_their_row(folder, text, words):
    with pytest.raises(InputError, match=re.escape(words)):
        load(folder, text)


def test_estimator_start_anywhere_sets_the_start_anywhere_settings(folder):
    """[estimator] start = "anywhere": the chosen start-anywhere settings (the C filter built
    from the config too), each under a key the table sets."""
    from ecmgen.config import START_ANYWHERE

    cfg = load(folder, HEAD + "[estimator]\nstart = \"anywhere\"\nmodel_error = 0.2\n")
    got = {k: getattr(cfg.estimator, k) for k in START_ANYWHERE}
    assert got == dict(START_ANYWHERE, model_error=0.2)
    assert load(folder, HEAD).estimator.start_polarization_c == 0.0
    with pytest.raises(InputError, match="needs start_polarization_c above 0"):
        load(folder, HEAD + "[estimator]\nstart = \"anywhere\"\nstart_polarization_c = 0\n")


def test_the_loader_lists_and_defaults_are_the_schema_rows():
    est = BY_NAME["estimator"]
    # "start" is the one key that is not a field: it sets the start-anywhere fields
    assert [k.name for k in est.keys if k.name != "start"] == [f.name for f in
                                                              fields(EstimatorConfig)]
    for f in fields(EstimatorConfig):
        shown = est.key(f.name).default
        if isinstance(f.default, bool):
            assert shown == str(f.default).lower()
        elif isinstance(f.default, str):
            assert shown == f'"{f.default}"'
        elif f.default is not None:
            assert float(shown.split()[0]) == f.default, f.name
    assert est.key("filter").choices == ESTIMATOR_FILTERS
    assert BY_NAME["c"].key("estimator").choices == C_ESTIMATORS
    from ecmgen.data.measure import CURRENT_SIGNS, ColumnMap
    # [data.columns.files]: tables of these keys by file, not a key of the map
    assert [k.name for k in BY_NAME["data.columns"].keys if not k.keys_of] == [
        f.name for f in fields(ColumnMap)]
    assert set(BY_NAME["data.columns"].key("current_sign").choices) == set(CURRENT_SIGNS)
    from ecmgen.model.effects import EFFECT_TYPES
    assert set(BY_NAME["diagnose"].key("effects").choices) == set(EFFECT_TYPES)
    from ecmgen.model.model import SURFACE_SOC_GAIN_MAX
    assert BY_NAME["model"].key("surface_soc_gain").range == (0.0, SURFACE_SOC_GAIN_MAX)
    for s in SECTIONS:
        for k in s.keys:
            assert k.help and k.kind, (s.name, k.name)


def test_diagnose_options_know_the_schema_keys():
    from ecmgen.diagnosis.search import diagnose_options

    keys = {k.name for k in BY_NAME["diagnose"].keys}
    with pytest.raises(InputError, match="unknown key"):
        diagnose_options({"x": 1}, "c.toml")
    for k in keys:      # each is known to diagnose_options (a bad value, never unknown)
        with pytest.raises(InputError) as exc:
            diagnose_options({k: object()}, "c.toml")
        assert "unknown key" not in str(exc.value)


def test_docs_config_reference_is_the_generated_one():
    """docs/config.md's reference is `ecmgen config --explain`'s text: edit the schema (and
    paste its output), never the page alone."""
    text = (REPO / "docs" / "config.md").read_text()
    start = text.index("<!-- generated from src/ecmgen/config/schema.py")
    start = text.index("\n", start) + 1
    end = text.index("<!-- end of the generated config reference -->")
    assert text[start:end] == reference()


def test_config_explain_prints_the_reference(capsys):
    assert main(["config", "--explain"]) == 0
    assert capsys.readouterr().out == reference()


def test_ecmgen_alone_lists_the_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: ecmgen COMMAND")
    lines = err.splitlines()
    for name in ("build", "validate", "estimate", "codegen", "diagnose", "config"):
        assert any(line.split()[:1] == [name] and len(line.split()) > 2 for line in lines), name


def test_every_config_example_in_the_readme_and_docs_passes_the_schema():
    """The TOML examples of the README and docs/ use only keys the schema knows, with
    valid values."""
    import tomllib

    from ecmgen.config.schema import check_config

    pages = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    blocks = [(p.name, b) for p in pages
              for b in re.findall(r"```toml\n(.*?)```", textwrap.dedent(p.read_text()), re.S)]
    assert len(blocks) >= 4
    for page, block in blocks:
        check_config(tomllib.loads(textwrap.dedent(block)))

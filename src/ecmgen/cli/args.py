"""The parsers of `ecmgen`: each command's arguments, bound to its function in
:mod:`ecmgen.cli.commands` (looked up on every call of :func:`parser`)."""

from __future__ import annotations

import argparse
import sys

from .._version import __version__
from . import commands

DESCRIPTION = "`ecmgen` command line: a thin layer over the library (see ecmgen.pipeline)."


class _Parser(argparse.ArgumentParser):
    """Bad arguments are bad input too: one line ``ecmgen: error: ...``, exit 2."""

    def error(self, message):
        where = self.prog.removeprefix("ecmgen").strip()
        if not where and "required: command" in message:     # `ecmgen` alone
            print(self.command_list(), file=sys.stderr)
            sys.exit(2)
        print(f"ecmgen: error: {where + ': ' if where else ''}{' '.join(message.split())}",
              file=sys.stderr)
        sys.exit(2)

    def command_list(self) -> str:
        """`ecmgen` alone: what it does and each command with its one-line help."""
        actions = self._subparsers._group_actions[0]
        helps = {a.dest: a.help for a in actions._choices_actions}
        width = max(len(n) for n in actions.choices)
        return "\n".join(["usage: ecmgen COMMAND [options]   (ecmgen COMMAND --help)", "",
                          "commands:"] + [f"  {n:<{width}}  {helps.get(n, '')}"
                                          for n in actions.choices])


def parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ecmgen", description=DESCRIPTION)
    p.add_argument("--version", action="version", version=f"ecmgen {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    # one function per command, in the order `ecmgen` alone lists them
    for add in (_build_args, _dcir_args, _fit_args, _validate_args, _estimate_args,
                _codegen_args, _verify_args, _diagnose_args, _fleet_args, _age_args,
                _config_args):
        add(sub)
    return p


def _build_args(sub) -> None:
    b = sub.add_parser("build", help="run the whole chain from a config file")
    b.add_argument("config")
    b.add_argument("--out", help="output folder (default: ecmgen-out beside the config)")
    b.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    b.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing on success but warnings (on stderr)")
    b.add_argument("--no-plots", action="store_true")
    b.add_argument("--no-c", action="store_true", help="skip C generation")
    b.add_argument("--strict", action="store_true",
                   help="fail (exit 2, nothing written) when the best model's tables are not "
                        "smooth and positive")
    b.set_defaults(func=commands.cmd_build)


def _dcir_args(sub) -> None:
    d = sub.add_parser("dcir", help="extract the DC-IR table of a pulse test")
    d.add_argument("pulses", nargs="?", help="the pulse test (default with --config: its "
                                             "data.pulses)")
    d.add_argument("--config", help="a build config: its column mapping, capacity, start "
                                    "SOC and [dcir] settings (the table build writes)")
    d.add_argument("--capacity-ah", type=float, help="cell capacity (needed without --config)")
    d.add_argument("--soc0", type=float, help="SOC at the start of the test (default 1.0, "
                                              "or as the build with --config)")
    d.add_argument("--times", type=float, nargs="+",
                   help="DC-IR times in s (default 0.1 1 3 6 10, or [dcir] times_s)")
    d.add_argument("--out", help="CSV path (default: stdout)")
    d.add_argument("-q", "--quiet", action="store_true", help="no notes on stderr")
    d.set_defaults(func=commands.cmd_dcir)


def _fit_args(sub) -> None:
    f = sub.add_parser("fit", help="fit a model.json from a config file")
    f.add_argument("config")
    f.add_argument("--method", choices=["ga", "lm", "curve"])
    f.add_argument("--out", default="model.json")
    f.add_argument("-q", "--quiet", action="store_true")
    f.set_defaults(func=commands.cmd_fit)


def _validate_args(sub) -> None:
    v = sub.add_parser("validate", help="simulate a model over a measured cycle")
    v.add_argument("model")
    v.add_argument("cycle")
    v.add_argument("--soc0", type=float, help="start SOC (default: from the OCV)")
    v.add_argument("--temperature-c", type=float, default=None,
                   help="cell temperature in degC for a file without a temperature column")
    v.add_argument("--equivalent-full-cycles", type=float, default=None, metavar="EFC",
                   help="the cell's age, for a model with an ageing law (default: fresh)")
    v.add_argument("--json", action="store_true")
    v.add_argument("--plot", help="write measured vs simulated PNG here")
    v.add_argument("--config", help="a build config whose [data.columns] maps the cycle's CSV")
    v.add_argument("--window-s", type=float, nargs=2, metavar=("T0", "T1"),
                   help="validate on the rows with T0 <= time <= T1 s (the file's own time)")
    v.add_argument("-q", "--quiet", action="store_true", help="(no progress is shown anyway)")
    v.set_defaults(func=commands.cmd_validate)


def _estimate_args(sub) -> None:
    e = sub.add_parser("estimate", help="run the SOC filter over a measured cycle and "
                                        "compare it with coulomb counting")
    e.add_argument("model")
    e.add_argument("cycle")
    e.add_argument("--soc0-guess", type=float, help="start SOC the filter is told "
                   "(default: --soc0)")
    e.add_argument("--soc0", type=float, help="true start SOC, for the reference SOC by "
                   "coulomb counting the measured current (default: from the OCV)")
    e.add_argument("--current-offset-a", type=float, default=0.0,
                   help="offset added to the current the filter sees, A")
    e.add_argument("--current-gain", type=float, default=1.0,
                   help="gain applied to the current the filter sees")
    e.add_argument("--temperature-c", type=float, default=None,
                   help="cell temperature in degC for a file without a temperature column")
    e.add_argument("--filter", choices=["ekf", "ukf"],
                   help="override the config's estimator.filter (default ekf)")
    e.add_argument("--config", help="a build config: its [estimator] settings and the "
                   "[data.columns] of the cycle's CSV")
    e.add_argument("--window-s", type=float, nargs=2, metavar=("T0", "T1"),
                   help="start the filter at T0 (the file's own time) and run it to T1; "
                        "--soc0 stays the SOC at the file's start, --soc0-guess is the "
                        "guess at T0")
    e.add_argument("--start", choices=["rested", "anywhere"],
                   help="how the record starts: rested (its first voltage read as the OCV) "
                        "or anywhere (under load or mid-relaxation: the start-anywhere "
                        "settings where [estimator] sets none); default: the config's, "
                        "anywhere when the record (or --window-s) opens unsettled")
    e.add_argument("--out", help="write time_s,soc,soc_sigma,voltage_pred_v,soc_ref here")
    e.add_argument("--json", action="store_true")
    e.add_argument("--quiet", action="store_true", help="(no progress is shown anyway)")
    e.set_defaults(func=commands.cmd_estimate)


def _codegen_args(sub) -> None:
    c = sub.add_parser("codegen", help="write the C of a model.json (e.g. an augmented one)")
    c.add_argument("model")
    c.add_argument("--out", required=True, help="folder for the .h/.c and runtime headers")
    c.add_argument("--prefix", default="ecm", help="C symbol prefix")
    c.add_argument("--numeric", choices=["float", "fixed"], default="float")
    c.add_argument("--dt-s", type=float, help="fixed step in s (default: variable dt)")
    c.add_argument("--estimator", choices=["none", "ekf"], default="none",
                   help="also generate the SOC filter <prefix>_est_f32.h/.c (float, "
                        "variable dt; the [estimator] defaults)")
    for what in ("ocv", "rc"):
        c.add_argument(f"--{what}-soc-step", type=int, default=1, metavar="N",
                       help=f"flash: the {what.upper()} table{'s' if what == 'rc' else ''} on "
                            "every N-th SOC breakpoint (and the last; [c] "
                            f"{what}_soc_step)")
    c.add_argument("-q", "--quiet", action="store_true", help="do not list the files written")
    c.set_defaults(func=commands.cmd_codegen)


def _verify_args(sub) -> None:
    v = sub.add_parser("verify", help="check your copy of the generated C against the build's "
                       "golden vectors (exit 0 pass, 1 fail, 2 bad input)")
    v.add_argument("golden", help="a build's c/float or c/fixed folder (or the build folder, "
                   "or one <prefix>_ecm_<s>_vectors.h)")
    v.add_argument("--c", dest="csrc", help="folder of your copy of the C (<prefix>_ecm_<s>.c "
                   "and its headers; default: the golden folder)")
    v.add_argument("--cc", help="C compiler command (default: cc)")
    v.add_argument("--cflags", help="compiler flags, one string (default: "
                   "'-std=c99 -O2 -ffp-contract=off')")
    v.add_argument("--run", help="command that runs the test program, e.g. an emulator "
                   "(default: run it directly)")
    v.set_defaults(func=commands.cmd_verify)


def _diagnose_args(sub) -> None:
    g = sub.add_parser("diagnose", help="find, add and check missing model effects")
    g.add_argument("config")
    g.add_argument("--out")
    g.add_argument("--json", action="store_true")
    g.add_argument("-q", "--quiet", action="store_true")
    g.add_argument("--no-plots", action="store_true")
    g.set_defaults(func=commands.cmd_diagnose)


def _fleet_args(sub) -> None:
    fl = sub.add_parser("fleet", help="build every cell x check-up of a manifest on Dask and "
                        "tabulate their trends (exit 0 all built, 1 some rows failed, 2 bad "
                        "input)")
    fl.add_argument("manifest", help="CSV: cell,checkup,config[,cycles,throughput_ah,date]")
    fl.add_argument("--out", required=True, metavar="DIR", help="output folder: <cell>/<checkup>/ "
                    "per row, fleet.csv, fleet.parquet, ageing.csv, failures.csv, trend plots")
    fl.add_argument("--scheduler", metavar="ADDRESS", help="address of a running Dask scheduler (default: a "
                    "local cluster)")
    fl.add_argument("--workers", type=int, metavar="N", help="local worker processes (default: one per "
                    "core); with --scheduler, wait for this many workers")
    fl.add_argument("--soc", type=float, nargs="+", default=[0.2, 0.5, 0.8], metavar="S",
                    help="SOC points of the fleet table (default 0.2 0.5 0.8)")
    fl.add_argument("--temperature-c", type=float, nargs="+", default=[25.0], metavar="T",
                    help="temperature points of the fleet table, degC (default 25; a "
                         "one-temperature model gives its own table)")
    fl.add_argument("--build-plots", action="store_true", help="each row's build plots too "
                    "(none by default)")
    fl.add_argument("--no-plots", action="store_true", help="no trend plots")
    fl.add_argument("--no-c", action="store_true", help="no C for any row")
    fl.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    fl.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    fl.set_defaults(func=commands.cmd_fleet)


def _age_args(sub) -> None:
    ag = sub.add_parser("age", help="fit the fleet's ageing law (resistance and capacity over "
                        "equivalent full cycles) into a model.json")
    ag.add_argument("fleet_dir", help="the --out folder of `ecmgen fleet` (its fleet.csv)")
    ag.add_argument("--out", required=True, metavar="MODEL.json", help="the aged model")
    ag.add_argument("--base", metavar="MODEL.json", help="the model the law is written into "
                    "(default: the first non-outlier cell's model at its first check-up)")
    ag.set_defaults(func=commands.cmd_age)


def _config_args(sub) -> None:
    k = sub.add_parser("config", help="print the config reference (every section and key)")
    k.add_argument("--explain", action="store_true", help="every key: type, unit, range, "
                   "default, meaning (markdown; docs/config.md holds this text)")
    k.set_defaults(func=commands.cmd_config)

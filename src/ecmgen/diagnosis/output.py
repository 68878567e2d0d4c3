"""What ``diagnose`` writes: the augmented model.json, report.md, diagnose.json and the
two plots (the base residual against each effect's signature; measured vs base vs
augmented voltage on the held-out part).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..files import json_text, write_atomic
from ..model import effects as fx
from ..model.rc import rc_recurrence
from ..plots.style import MEASURED, _plt
from .result import UNEXPLAINED_RATIO
from .search import DiagnoseResult, _lowpass


# -- outputs: model.json, plots, report.md ---------------------------------------------------

EFFECT_WORDS = {
    fx.Hysteresis.name: "OCV hysteresis: the voltage depends on the sign and history of the "
                        "current (one-state Plett model)",
    fx.CurrentDependentResistance.name: "resistance falling with |I| (Butler-Volmer-like "
                                        "charge transfer)",
    fx.ExtraRc.name: "a slow polarisation (a further RC pair with a time constant of minutes) "
                     "that 10 s pulses cannot see",
    fx.CapacityError.name: "the capacity used for coulomb counting is off",
    fx.TemperatureDependence.name: "resistances falling as the cell warms (Arrhenius)",
    "current_offset": "a fault of the record, corrected in the data (model.json is the model "
                      "without it)",
    "current_gain": "a fault of the record, corrected in the data (model.json is the model "
                    "without it)",
    "voltage_lag": "a fault of the record: the voltage channel lags the current; the model's "
                   "voltage is compared through the same lag (model.json is the model "
                   "without it)",
    "ocv_error": "the OCV table is off; model.json carries it corrected",
    "entropic_ocv": "the OCV table lacks its move with temperature (entropic); model.json "
                    "carries it as an OCV over temperature",
}


def _signature_x(name: str, result: DiagnoseResult):
    """x values and label of an effect's signature plot over the fit part."""
    s = result.fit_series
    sim = result.base_fit_sim
    stop = result.fit_stop
    dt = np.diff(s.time_s, prepend=s.time_s[0])
    i = s.current_a
    q = result.base_model.capacity_ah
    g = result.signatures[name].guess
    if name == fx.Hysteresis.name:
        ch = np.where(sim.charging, 1.0, -1.0)
        a = np.exp(-np.abs(i) * dt / (3600.0 * g.get("decay_ah", 0.05 * q)))
        x = rc_recurrence(a, (1 - a) * ch, ch[0])
        return x[:stop], f"direction memory h (decay {g.get('decay_ah', 0.05 * q):.3g} Ah)"
    if name == fx.CurrentDependentResistance.name:
        return i[:stop], "current [A]"
    if name == fx.ExtraRc.name:
        tau = g.get("tau_s", 600.0)
        return _lowpass(dt, i, tau)[:stop], f"current low-pass filtered, tau {tau:.0f} s [A]"
    if name == fx.CapacityError.name:
        return (np.cumsum(i * dt) / 3600.0)[:stop], "charge throughput [Ah]"
    if name == fx.TemperatureDependence.name:
        if s.temperature_c is None:
            return None, "temperature (not in the data)"
        return s.temperature_c[:stop], "cell temperature [degC]"
    raise ValueError(name)


def _binned(x, y, n=25):
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 10 or np.ptp(x) <= 0:
        return np.array([]), np.array([])
    edges = np.quantile(x, np.linspace(0, 1, n + 1))
    edges = np.unique(edges)
    k = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1)
    sy = np.bincount(k, weights=y, minlength=edges.size - 1)
    sx = np.bincount(k, weights=x, minlength=edges.size - 1)
    m = cnt > 0
    return sx[m] / cnt[m], sy[m] / cnt[m]


def plot_signatures(result: DiagnoseResult, path: Path) -> Path:
    """Residual of the base model (fit part) against each effect's signature."""
    plt = _plt()
    res = (result.fit_series.voltage_v - result.base_fit_sim.voltage_v)[:result.fit_stop] * 1e3
    names = list(fx.EFFECT_NAMES)
    fig, axes = plt.subplots(2, 3, figsize=(14, 7.5))
    rng = np.random.default_rng(0)
    pick = rng.choice(res.size, size=min(res.size, 4000), replace=False)
    for ax, name in zip(axes.flat, names):
        sig = result.signatures[name]
        x, label = _signature_x(name, result)
        if x is None:
            ax.text(0.5, 0.5, sig.detail, ha="center", va="center", transform=ax.transAxes,
                    fontsize=9, wrap=True)
            ax.set_xticks([])
            ax.set_yticks([])
        else:
            ax.plot(x[pick], res[pick], ".", ms=2, alpha=0.25, color="0.5")
            bx, by = _binned(x, res)
            ax.plot(bx, by, "o-", color="C3", ms=3, lw=1.2, label="binned mean")
            ax.axhline(0, color="k", lw=0.6)
            lo, hi = np.percentile(res, [1, 99])
            pad = 0.1 * (hi - lo + 1e-3)
            ax.set_ylim(lo - pad, hi + pad)
        added = name in result.effects
        ax.set_title(f"{name}  (explains {100 * sig.r2:.0f} %)" + ("  ADDED" if added else ""),
                     fontsize=9, color="C2" if added else "k")
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel("measured - base [mV]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    t = result.fit_series.time_s[:result.fit_stop]
    ax = axes.flat[5]
    ax.plot(t, res, lw=0.5, color="C0")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_title("residual over time (fit part)", fontsize=9)
    ax.set_xlabel("time [s]", fontsize=8)
    ax.set_ylabel("measured - base [mV]", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    fig.suptitle("Where the base model misses: residual against each effect's signature",
                 fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_comparison(result: DiagnoseResult, path: Path) -> Path:
    """Held-out part: measured vs base vs augmented voltage, the errors, MAE per step."""
    plt = _plt()
    a = result.judge_start
    s = result.judge_series
    t = s.time_s[a:]
    vm = s.voltage_v[a:]
    vb = result.base_judge_sim.voltage_v[a:]
    va = result.judge_sim.voltage_v[a:]
    fig = plt.figure(figsize=(13, 9))
    gs = fig.add_gridspec(3, 4)
    ax0 = fig.add_subplot(gs[0, :])
    ax0.plot(t, vm, label="measured", **dict(MEASURED, lw=0.8))
    ax0.plot(t, vb, lw=0.7, color="C1", label=f"base (MAE {result.mae_before_v * 1e3:.2f} mV)")
    ax0.plot(t, va, lw=0.7, color="C2",
             label=f"with {', '.join(result.effects) or 'no effects'} "
                   f"(MAE {result.mae_after_v * 1e3:.2f} mV)")
    ax0.set_ylabel("voltage [V]")
    ax0.legend(fontsize=8, loc="lower left")
    ax0.set_title(f"held out: {result.split}", fontsize=9)
    ax0.grid(alpha=0.3)
    ax1 = fig.add_subplot(gs[1, :], sharex=ax0)
    ax1.plot(t, (vb - vm) * 1e3, lw=0.5, color="C1", label="base")
    ax1.plot(t, (va - vm) * 1e3, lw=0.5, color="C2", label="augmented")
    ax1.axhline(0, color="k", lw=0.6)
    e = np.concatenate([vb - vm, va - vm]) * 1e3
    lo, hi = np.percentile(e, [0.5, 99.5])
    ax1.set_ylim(lo - 0.1 * (hi - lo + 1), hi + 0.1 * (hi - lo + 1))
    ax1.set_ylabel("simulated - measured [mV]")
    ax1.set_xlabel("time [s]")
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    ax2 = fig.add_subplot(gs[2, :2])
    labels = ["base"] + [f"+ {st.name}" for st in result.steps]
    maes = [result.mae_before_v * 1e3] + [st.mae_after_v * 1e3 for st in result.steps]
    ax2.bar(range(len(maes)), maes, color=["C1"] + ["C2"] * len(result.steps))
    ax2.set_xticks(range(len(maes)))
    ax2.set_xticklabels(labels, fontsize=8, rotation=15)
    ax2.set_ylabel("held-out MAE [mV]")
    ax2.grid(alpha=0.3, axis="y")
    ax3 = fig.add_subplot(gs[2, 2:])
    rounds = sorted({c.round for c in result.candidates})
    for r in rounds:
        cs = [c for c in result.candidates if c.round == r and math.isfinite(c.judge_mae_v)]
        ax3.plot([c.judge_mae_v * 1e3 for c in cs], [c.name for c in cs], "o",
                 label=f"round {r}")
    ax3.axvline(result.mae_before_v * 1e3, color="C1", lw=0.8, ls="--")
    ax3.set_xlabel("held-out MAE with the candidate [mV]")
    ax3.tick_params(labelsize=7)
    ax3.legend(fontsize=7)
    ax3.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _mv(x: float) -> str:
    return f"{x * 1e3:.2f} mV"


def report_text(result: DiagnoseResult, model_name: str = "model.json") -> str:
    """report.md: what is missing, in words, with the numbers behind it."""
    lines = ["# ecmgen diagnose", ""]
    fit_name = Path(result.fit_series.source).name or "the cycle"
    lines += [f"Fitted on: {fit_name} (first {result.fit_stop} samples)",
              f"Held out: {result.split}",
              f"Start SOC {result.soc0:.4f} (held-out record {result.judge_soc0:.4f}); "
              f"voltage noise {_mv(result.noise_v)} (std, from the rests); "
              f"run time {result.seconds:.1f} s", ""]
    lines += ["## Verdict", ""]
    lines += _verdict_lines(result, model_name)
    lines += ["", "## Signatures in the base residual (fit part)", "",
              "| effect | explains | what was regressed |", "|---|---|---|"]
    for name, sig in sorted(result.signatures.items(), key=lambda kv: -kv[1].r2):
        share = f"{100 * sig.r2:.1f} %" if sig.applicable else "n/a"
        lines.append(f"| {name} | {share} | {sig.detail} |")
    lines += _candidate_lines(result)
    if result.steps:
        lines += ["", "## Effect parameters (as in the augmented model)", ""]
        for st in result.steps:
            params = ", ".join(f"{k} = {v:.6g}" for k, v in st.effect.params().items())
            lines.append(f"- {st.name}: {params}")
    lines += ["", "## Plots", "", "- diagnose-signatures.png: the base residual against each "
              "effect's signature", "- diagnose-comparison.png: measured vs base vs augmented "
              "on the held-out part, and the MAE per step"]
    for n in result.notes:
        lines.append(f"- note: {n}")
    return "\n".join(lines) + "\n"


def _verdict_lines(result: DiagnoseResult, model_name: str) -> list[str]:
    """report.md's verdict: what was named, or why nothing was."""
    lines: list[str] = []
    if result.steps:
        lines.append(f"The base model misses {len(result.steps)} effect(s); each was added "
                     "only because it lowered the error on data the fit did not see by more "
                     "than noise explains:")
        lines.append("")
        for k, st in enumerate(result.steps, 1):
            words = EFFECT_WORDS[st.name]
            if hasattr(st.effect, "words"):
                words = f"{st.effect.words()}: {words}"
            lines.append(f"{k}. **{st.name}** - {words}. Held-out MAE "
                         f"{_mv(st.mae_before_v)} -> {_mv(st.mae_after_v)} "
                         f"({100 * (1 - st.mae_after_v / st.mae_before_v):.0f} % lower; "
                         f"99 % lower bound of the gain {_mv(st.ci_low_v)}).")
        lines += ["", f"Held-out MAE of the base model {_mv(result.mae_before_v)}, of the "
                      f"augmented model ({model_name}) {_mv(result.mae_after_v)}."]
    elif result.cannot_tell:
        lines.append(f"Cannot tell: {result.verdict}. {model_name} is the model without "
                     "them.")
    elif result.not_named:
        tried = ", ".join(st.name for st in result.not_named)
        lines.append(f"Unexplained: {tried} passed the held-out test but left "
                     f"{_mv(result.not_named[-1].mae_after_v)}, more than {UNEXPLAINED_RATIO:g} x "
                     f"the larger of "
                     f"the voltage noise ({_mv(result.noise_v)}) and the base's RMS on its "
                     f"pulse test ({_mv(result.misfit_v)}): what the record shows is not what "
                     f"they describe (an effect diagnose has no candidate for, or more than "
                     f"it can tell apart), so none is named. {model_name} is the base model "
                     f"unchanged.")
    elif result.unexplained:
        lines.append(f"Unexplained: the held-out MAE ({_mv(result.mae_before_v)}) is "
                     f"{result.mae_before_v / result.floor_v:.0f} x {_floor_words(result)}"
                     f", and no effect that diagnose knows lowered it by "
                     f"more than noise explains. {model_name} is the base model unchanged.")
    else:
        lines.append(f"Nothing is missing that this data can show: no effect lowered the "
                     f"held-out MAE ({_mv(result.mae_before_v)}) by more than noise explains. "
                     f"{model_name} is the base model unchanged.")
    if result.steps and result.cannot_tell:
        lines += ["", f"Then: {' or '.join(result.cannot_tell[0])} - the data cannot tell them "
                      f"apart; {model_name} has neither."]
    if result.steps and result.unexplained:
        lines += ["", f"Unexplained: after them the held-out MAE ({_mv(result.mae_after_v)}) is "
                      f"still {result.mae_after_v / result.floor_v:.0f} x "
                      f"{_floor_words(result)}: part of the error is nothing diagnose knows."]
    return lines


def _candidate_lines(result: DiagnoseResult) -> list[str]:
    """report.md's table of every candidate tried, round by round."""
    lines = ["", "## Candidates tried", "",
              "| round | effect | held-out MAE | gain | gain lower bound | kept | why not |",
              "|---|---|---|---|---|---|---|"]
    kept = {(k + 1, st.name) for k, st in enumerate(result.steps)}
    for c in result.candidates:
        yes = (c.round, c.name) in kept
        why = c.message or ("" if yes else "passed, but another candidate did better")
        lines.append(f"| {c.round} | {c.name} | {_mv(c.judge_mae_v)} | {_mv(c.gain_v)} "
                     f"({100 * c.rel_gain:.1f} %) | {_mv(c.ci_low_v)} | "
                     f"{'yes' if yes else 'no'} | {why} |")
    return lines


def _floor_words(result: DiagnoseResult) -> str:
    if result.misfit_v is not None and result.misfit_v > result.noise_v:
        return (f"the base's RMS on its pulse test ({1e3 * result.misfit_v:.2f} mV, above the "
                f"voltage noise {1e3 * result.noise_v:.2f} mV)")
    return f"the voltage noise ({1e3 * result.noise_v:.2f} mV)"


def write_diagnose_outputs(result: DiagnoseResult, out_dir: str | Path, *, plots: bool = True,
                           model_name: str = "model.json") -> list[Path]:
    """Write the augmented model, report.md, diagnose.json and the plots into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = [result.model.save(out / model_name)]
    report = out / "report.md"
    write_atomic(report, report_text(result, model_name))
    files.append(report)
    js = out / "diagnose.json"
    write_atomic(js, json_text(result.to_json_dict(out / model_name), indent=1) + "\n")
    files.append(js)
    if plots:
        files.append(plot_signatures(result, out / "diagnose-signatures.png"))
        files.append(plot_comparison(result, out / "diagnose-comparison.png"))
    return files

"""What a diagnosis found: the signatures, the candidates tried, the effects named."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from ..data.measure import TimeSeries
from ..model.model import EcmModel
from ..model.simulate import SimResult

# -- results ------------------------------------------------------------------------------

# held-out MAE over the noise std above which the error left is called unexplained: a model
# that explains the data leaves about 0.8 x the std of white noise plus its own small misfit
# (the control cells of ../shared/diagnose-suite end at 1.3-1.6 x)
UNEXPLAINED_RATIO = 3.0


# what each candidate's signature needs in a record (the look-alike verdict: "a record with
# ... would tell them apart")
TELLS = {
    "hysteresis": "long rests after a charge and after a discharge at one SOC",
    "extra_rc": "a rest of an hour after a long current",
    "diffusion": "rests of an hour after currents of several lengths",
    "current_dependent_resistance": "pulses at several C-rates",
    "capacity_error": "a full charge and discharge between rested voltages",
    "temperature_dependence": "the same pulses at two temperatures",
    "current_offset": "a long rest with its current logged",
    "current_gain": "pulses of equal charge at two currents",
    "ocv_error": "a slow (C/20) OCV test of this cell",
    "entropic_ocv": "rests at one SOC at two temperatures",
    "voltage_lag": "current steps with both channels logged ten times faster",
}


def _is_correction(effect) -> bool:
    """A fault of the record (a sensor's, the OCV table's), not an effect in the model."""
    return hasattr(effect, "words")


def _correction_words(st) -> str:
    where = ("model.json carries the OCV corrected" if st.effect.kind != "sensor" else
             "the model's voltage compared through it" if st.name == "voltage_lag" else
             "corrected in the data")
    return (f"{st.name}: {st.effect.words()}; {where}, the held-out error is "
            f"{st.mae_after_v * 1e3:.2f} mV")


def explained_floor(noise_v: float, misfit_v: float | None) -> float:
    """What a model that misses nothing leaves: the noise, or the base's own misfit on the
    test that made it where that is larger and known."""
    return max(noise_v, misfit_v or 0.0)


@dataclass(frozen=True)
class Signature:
    """How much of the base residual (fit part) one effect's signature explains."""

    name: str
    applicable: bool
    r2: float                 # share of the residual's sum of squares explained (0..1)
    detail: str               # what was regressed on what, best shape parameter
    guess: dict = field(default_factory=dict)   # starting values for the fit (native units)


@dataclass(frozen=True)
class Candidate:
    """One effect tried in one greedy round."""

    round: int
    name: str
    effect: object | None
    fit_mae_v: float          # MAE on the fit part with the candidate added
    judge_mae_v: float        # MAE on the held-out part
    gain_v: float             # held-out MAE before - after
    rel_gain: float           # gain_v / held-out MAE before
    ci_low_v: float           # lower confidence bound of gain_v (block bootstrap)
    passed: bool
    seconds: float
    message: str = ""


@dataclass(frozen=True)
class DiagnoseStep:
    """One effect added, with the held-out MAE before and after adding it."""

    name: str
    effect: object
    mae_before_v: float
    mae_after_v: float
    ci_low_v: float


@dataclass
class DiagnoseResult:
    base_model: EcmModel
    model: EcmModel                    # base + the effects added (in order)
    steps: tuple[DiagnoseStep, ...]
    candidates: tuple[Candidate, ...]
    signatures: dict[str, Signature]
    mae_before_v: float                # held-out MAE of the base model
    mae_after_v: float                 # held-out MAE of the augmented model
    fit_mae_before_v: float
    fit_mae_after_v: float
    noise_v: float                     # voltage noise (std) estimated from the rests
    split: str                         # how the held-out part was chosen, in words
    fit_series: TimeSeries
    judge_series: TimeSeries
    fit_stop: int                      # fit_series[:fit_stop] was fitted
    judge_start: int                   # judge_series[judge_start:] was judged
    soc0: float
    judge_soc0: float
    base_fit_sim: SimResult
    base_judge_sim: SimResult
    judge_sim: SimResult               # augmented model on the judge series
    seconds: float
    notes: tuple[str, ...] = ()
    misfit_v: float | None = None      # the base's RMS on the test that made it
    not_named: tuple[DiagnoseStep, ...] = ()   # passed, but left the error unexplained
    # look-alikes the held-out part could not tell apart (each a tuple of names, the
    # winner first), and the held-out error the winner left
    cannot_tell: tuple[tuple[str, ...], ...] = ()
    cannot_tell_mae_v: float | None = None
    # named in the search but not needed once later effects joined (ecmgen.diagnosis.prune)
    dropped: tuple = ()

    @property
    def effects(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.steps)

    @property
    def floor_v(self) -> float:
        """:func:`explained_floor` of this diagnosis."""
        return explained_floor(self.noise_v, self.misfit_v)

    @property
    def unexplained(self) -> bool:
        """The held-out error left is well above the floor (UNEXPLAINED_RATIO); where
        look-alikes could not be told apart, the error the best of them left."""
        left = self.cannot_tell_mae_v if self.cannot_tell else self.mae_after_v
        return bool(self.floor_v > 0 and left > UNEXPLAINED_RATIO * self.floor_v)

    @property
    def verdict(self) -> str:
        """One line: what was named, and whether the error left is noise."""
        left = (f"held-out error {self.mae_after_v * 1e3:.2f} mV against "
                f"{self.noise_v * 1e3:.2f} mV noise")
        if self.misfit_v is not None:
            left += f" and the base's {self.misfit_v * 1e3:.2f} mV RMS on its pulse test"
        added = [st.name for st in self.steps if not _is_correction(st.effect)]
        named = (f"added {', '.join(added)}; " if added else "") + "".join(
            f"{_correction_words(st)}; " for st in self.steps if _is_correction(st.effect))
        if self.cannot_tell:
            group = self.cannot_tell[0]
            return (f"{named}{' or '.join(group)} - the data cannot tell them apart (the "
                    f"first leaves {self.cannot_tell_mae_v * 1e3:.2f} mV held out against "
                    f"{self.noise_v * 1e3:.2f} mV noise); a record with "
                    f"{' or '.join(TELLS.get(n, n) for n in group)} would; none is named")
        if self.not_named:
            tried = ", ".join(st.name for st in self.not_named)
            return (f"unexplained: {left}; {tried} lowered it to "
                    f"{self.not_named[-1].mae_after_v * 1e3:.2f} mV, still above "
                    f"{UNEXPLAINED_RATIO:g}x that: not named (an effect diagnose has no "
                    "candidate for, or more than it can tell apart)")
        if self.unexplained:
            return (f"{named}unexplained: {left}; no further effect that diagnose knows "
                    "lowers it by more than noise explains")
        if self.steps:
            return f"{named}{left}"
        return f"nothing is missing that this data can show: {left}"

    def to_json_dict(self, model_path: str | Path | None = None) -> dict:
        def f(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            "effects": [{"name": s.name, "correction": _is_correction(s.effect),
                         "mae_before_v": f(s.mae_before_v),
                         "mae_after_v": f(s.mae_after_v), "gain_ci_low_v": f(s.ci_low_v),
                         "params": s.effect.params()} for s in self.steps],
            "mae_before_v": f(self.mae_before_v),
            "mae_after_v": f(self.mae_after_v),
            "fit_mae_before_v": f(self.fit_mae_before_v),
            "fit_mae_after_v": f(self.fit_mae_after_v),
            "noise_v": f(self.noise_v),
            "base_misfit_v": f(self.misfit_v),
            "not_named": [{"name": s.name, "mae_after_v": f(s.mae_after_v),
                           "params": s.effect.params()} for s in self.not_named],
            "cannot_tell": [list(g) for g in self.cannot_tell],
            "cannot_tell_mae_v": f(self.cannot_tell_mae_v),
            "dropped": [{"name": d.name, "mae_with_v": f(d.mae_with_v),
                         "mae_without_v": f(d.mae_without_v)} for d in self.dropped],
            "unexplained": self.unexplained,
            "verdict": self.verdict,
            "held_out": self.split,
            "signatures": {k: {"applicable": s.applicable, "r2": f(s.r2), "detail": s.detail}
                           for k, s in self.signatures.items()},
            "candidates": [{"round": c.round, "name": c.name, "judge_mae_v": f(c.judge_mae_v),
                            "gain_v": f(c.gain_v), "rel_gain": f(c.rel_gain),
                            "gain_ci_low_v": f(c.ci_low_v), "passed": c.passed,
                            "message": c.message} for c in self.candidates],
            "seconds": round(self.seconds, 2),
            "model": None if model_path is None else str(model_path),
        }



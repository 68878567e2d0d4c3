"""What the command line prints: progress on stderr (on a terminal one line rewritten in
place; in a log one line a stage), a build's notes grouped and counted (the full list is
in report.md), its one-screen validation table and its one-line summary.

Results go to stdout, progress, notes and warnings to stderr."""

from __future__ import annotations

import re
import shutil
import sys


class StderrProgress:
    """A progress callable: ``progress(msg)`` for a stage, ``progress.detail(msg)`` for a
    step within one. On a terminal both rewrite one status line, cleared by
    :meth:`close`; elsewhere (a log, CI) the stages are lines and the steps are left out."""

    def __init__(self, stream=None):
        self.stream = sys.stderr if stream is None else stream
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._shown = False

    def __call__(self, msg: str) -> None:
        self._show(msg)

    def detail(self, msg: str) -> None:
        if self.tty:
            self._show(msg)

    def _show(self, msg: str) -> None:
        line = f"[ecmgen] {msg}"
        if not self.tty:
            print(line, file=self.stream, flush=True)
            return
        width = shutil.get_terminal_size((100, 20)).columns - 1
        self.stream.write("\r\033[K" + line[:width])
        self.stream.flush()
        self._shown = True

    def close(self) -> None:
        """Clear the status line (a terminal), so what follows starts on a clean line."""
        if self._shown:
            self.stream.write("\r\033[K")
            self.stream.flush()
            self._shown = False


def quiet(_msg: str) -> None:
    """A progress callable that shows nothing."""


def detail_of(progress):
    """The callable for a step within a stage: ``progress.detail`` where the progress has
    one (StderrProgress), else ``progress`` itself."""
    return getattr(progress, "detail", progress)


# notes said once with their count: (pattern, what the count is of)
NOTE_GROUPS = (
    (re.compile(r"pulse at t=.* cut short after"),
     "{n} pulses cut short (shorter than the others of their direction) and left out"),
    (re.compile(r"the voltage lags the current by"),
     "{n} cycles: the measured voltage lags the current (not corrected)"),
)


def is_warning(note: str) -> bool:
    return "warning" in note.lower()


def note_lines(notes, report: str = "report.md") -> list[str]:
    """A build's notes for the terminal: each warning in full, the common kinds counted on
    one line each, and how many more the report lists."""
    lines, counts, rest = [], [0] * len(NOTE_GROUPS), 0
    for note in notes:
        if is_warning(note):
            lines.append(f"warning: {note}")
            continue
        for k, (pattern, _) in enumerate(NOTE_GROUPS):
            if pattern.search(note):
                counts[k] += 1
                break
        else:
            rest += 1
    lines += [f"note: {what.format(n=n)}" for n, (_, what) in zip(counts, NOTE_GROUPS) if n]
    if rest:
        lines.append(f"note: {rest} more note{'s' if rest > 1 else ''}: see {report}")
    return lines


def cycle_table(rows, best: str) -> str:
    """One line per validation cycle: its cell temperature over the drive and each
    method's MAE (``rows``: report.validation_rows)."""
    methods = list(dict.fromkeys(r[0] for r in rows))
    cycles = list(dict.fromkeys(r[1] for r in rows))
    mae = {(r[0], r[1]): r[2] for r in rows}
    temps = {r[1]: r[6] for r in rows}
    width = max([5] + [len(c) for c in cycles])
    names = [m + ("*" if m == best else "") for m in methods]
    head = (f"{'cycle':<{width}}  {'cell degC':>13}  MAE mV: "
            + "  ".join(f"{n:>7}" for n in names))
    lines = [head, "-" * len(head)]
    for c in cycles:
        tr = temps[c]
        t = f"{tr[0]:.1f}..{tr[1]:.1f}" if tr else "-"
        lines.append(f"{c:<{width}}  {t:>13}  {'':7} " + "  ".join(
            f"{mae[(m, c)]:7.2f}" if (m, c) in mae else f"{'-':>7}" for m in methods))
    lines.append("(* = model.json; RMSE, max and MAE over SOC > 10 % in report.md)")
    return "\n".join(lines)


def build_summary(result) -> str:
    """One line: the model written, its error range over the validation cycles, where."""
    vals = result.validations.get(result.best, {})
    maes = [v.overall.mae_v * 1e3 for v in vals.values()]
    fit = (f", MAE {min(maes):.1f}..{max(maes):.1f} mV over {len(maes)} cycle"
           f"{'s' if len(maes) > 1 else ''}" if len(maes) > 1
           else f", MAE {maes[0]:.1f} mV" if maes else "")
    return (f"model.json ({result.best}{fit}); {len(result.files)} files in "
            f"{result.out_dir} (open report.md)")

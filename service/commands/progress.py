"""How a running study reports itself on a terminal: a live bar per model on an interactive terminal (rich),
plain flushed lines in logs and CI; and the final table."""

from __future__ import annotations

import math
import os
import sys

from ardflow.ardcore.events import BurninRound, ModelDone, ModelEvent, Note, TrialDone


def done_words(log_evidence: float) -> str:
    """How a finished model reads: its ln Z, or that it is no result (the summary says why)."""
    if math.isfinite(log_evidence):
        return f"done: ln Z = {log_evidence:.3f}"
    return "refused: no result (the summary says why)"


def print_progress(ev: ModelEvent) -> None:
    """One line per event of a running study (stdout, flushed)."""
    m, p = ev.model, ev.event
    if isinstance(p, ModelDone):
        print(f"[{m}] {done_words(p.log_evidence)}", flush=True)
    elif isinstance(p, TrialDone):
        mark = "accepted" if p.accepted else "rejected"
        value = (f"ln Z <= {p.log_evidence:.3f}  {mark}" if p.bound
                 else f"ln Z = {p.log_evidence:.3f} +- {p.log_evidence_se:.3f}  {mark}" if math.isfinite(p.log_evidence)
                 else "ln Z is not a number: no result")
        print(f"[{m}] trial {p.iteration:>3}  {p.action:<40s} {value}", flush=True)
    elif isinstance(p, Note):
        print(f"[{m}]   {p.message}", flush=True)
    elif isinstance(p, BurninRound) and (p.round == 1 or p.round % 5 == 0):
        r = p.max_rhat
        print(f"[{m}]   burn-in round {p.round:>3}: max R-hat {r:.3f}, best ln post {p.best_lp:.2f}, "
              f"acceptance {p.acceptance:.2f}", flush=True)


def print_table(summary: dict) -> None:
    from ardflow.ardcore.sampling.diagnostics import Quality

    print(f"\n{'model':<12s} {'ln Z':>12s} {'se':>7s} {'GoF':>12s} {'EIG':>8s} {'P(M|d)':>8s} {'R-hat':>6s} "
          f"{'ESS':>6s}  kept / pruned")
    for r in summary["models"]:
        if r.get("refused"):  # no result: its numbers are not printed as if they were one
            print(f"{r['name']:<12s} refused: {r['refused']}")
            continue
        # the reported draws as ArviZ judged them: the worst R-hat and the smallest bulk or tail ESS
        rh, ess, _, _ = Quality().worst(r.get("diagnostics") or {})
        print(f"{r['name']:<12s} {r['log_evidence']:12.3f} {r['log_evidence_se']:7.3f} {r['goodness_of_fit']:12.3f} "
              f"{r['information_gain']:8.3f} {r['probability']:8.4f} {rh:6.3f} {min(ess, 1e6):6.0f}  "
              f"{r['kept']} / {r['pruned']}")
        for w in r["warnings"]:
            print(f"  warning: {w}")


class LiveProgress:
    """A progress callback: with an interactive terminal (and not ``CI``), a live bar per model (trials done
    of the maximiser's ``max_trials``, a cap the search usually stops well before, so no time left is shown;
    the elapsed time, the last trial's action and the best
    ln Z); otherwise :func:`print_progress`'s lines. Use as a context manager around the run."""

    def __init__(self, max_trials: int = 60, *, live: bool | None = None):
        self.max_trials = max_trials
        if live is None:
            live = sys.stdout.isatty() and not os.environ.get("CI") and os.environ.get("TERM") != "dumb"
        self.live = live
        self.bars: dict[str, int] = {}
        self.best: dict[str, float] = {}
        self._progress = None

    def __enter__(self):
        if self.live:
            try:
                from rich.progress import (
                    BarColumn,
                    Progress,
                    TextColumn,
                    TimeElapsedColumn,
                )
            except ImportError:  # rich is optional: plain lines
                self.live = False
                return self
            self._progress = Progress(TextColumn("[bold]{task.fields[model]:<10}"), BarColumn(),
                                      TextColumn("{task.completed:>3.0f} of at most {task.total:.0f} trials"),
                                      TimeElapsedColumn(),
                                      TextColumn("{task.fields[status]}"), transient=False)
            self._progress.__enter__()
        return self

    def __exit__(self, *exc):
        if self._progress is not None:
            self._progress.__exit__(*exc)
            self._progress = None

    def __call__(self, ev: ModelEvent) -> None:
        if self._progress is None:
            print_progress(ev)
            return
        m, p = ev.model, ev.event
        if m not in self.bars:
            self.bars[m] = self._progress.add_task(m, total=self.max_trials, model=m, status="starting")
        task = self.bars[m]
        if isinstance(p, TrialDone):
            if p.accepted and math.isfinite(p.log_evidence):
                self.best[m] = max(self.best.get(m, -math.inf), p.log_evidence)
            best = self.best.get(m)
            self._progress.update(task, advance=1, status=f"{p.action[:38]:<38}"
                                  + (f"  best ln Z {best:.2f}" if best is not None else ""))
        elif isinstance(p, BurninRound):
            self._progress.update(task, status=f"burn-in round {p.round}: max R-hat {p.max_rhat:.2f}")
        elif isinstance(p, ModelDone):
            self._progress.update(task, completed=self.max_trials, total=self.max_trials,
                                  status=done_words(p.log_evidence))
        elif isinstance(p, Note):
            self._progress.console.print(f"[{m}]   {p.message}")

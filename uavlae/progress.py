"""Training progress that shows wherever the run is watched.

On a terminal (stderr is a TTY and ``trainer.progress_bar`` is on) a tqdm bar advances with the
frames of every env step, so a batch of 1024 frames no longer sits at 0 until its last step.
Anywhere else (a sweep's job, a launcher's log, ``make long-sac > file``, or the bar turned off)
a log line every ``trainer.progress_every_s`` seconds says how far the run is::

    sac seed0: 51,200 / 400,000 frames (12.8%), 1,000 frames/s, ETA 5m49s; last evaluation at 50,176: DCR 0.297 CR 0.125 SLR 0.000

The first line comes ``trainer.progress_first_s`` after the start (a reader learns at once that the
run moves and how fast), the next ones every ``trainer.progress_every_s``. frames/s and the ETA
count this process's wall clock since it started (evaluations included, since they take the same
time again on the way to the end); a resumed run counts from where it resumed.

An evaluation reports the same way, by episodes (:class:`EpisodeProgress`)::

    sac_llm with its advisor: step 120, 3 of 8 episodes done, 42 s; advisor asked 40 of 64 rows
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Mapping
from typing import Any, TextIO

log = logging.getLogger(__name__)

SHOWN = ("DCR", "CR", "SLR")  # the last evaluation's metrics on the bar and in the lines


def format_duration(seconds: float) -> str:
    """``3725`` -> ``"1h02m"``, ``300`` -> ``"5m00s"``, ``42.4`` -> ``"42s"``."""
    s = int(round(max(seconds, 0.0)))
    if s >= 3600:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    if s >= 60:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s}s"


class Progress:
    """Frames done out of ``total``: a bar on a terminal, else a line every ``every_s`` seconds.

    Args:
        total: the run's frame budget.
        initial: frames done before this process (a resumed run's).
        name: what the lines call the run (method and seed).
        bar: show a bar when ``stream`` is a terminal.
        every_s: seconds between lines where there is no bar (0: no lines).
        first_s: seconds to the first line (None: ``every_s``; never later than ``every_s``).
        stream: where the bar draws (stderr).
        clock: seconds, for the tests (``time.monotonic``).
    """

    def __init__(self, total: int, initial: int = 0, *, name: str = "", bar: bool = True, every_s: float = 60.0,
                 first_s: float | None = None, stream: TextIO | None = None, clock: Any = time.monotonic):
        self.total, self.frames, self.name = int(total), int(initial), name
        self.start_frames, self.clock = int(initial), clock
        self.t0 = clock()
        self.every_s = float(every_s)
        self.next_line = self.t0 + min(self.every_s, self.every_s if first_s is None else float(first_s))
        self.last_eval: dict[str, float] = {}
        self.last_eval_frames: int | None = None
        stream = sys.stderr if stream is None else stream
        self.bar = None
        if bar and getattr(stream, "isatty", lambda: False)():
            from tqdm.auto import tqdm

            self.bar = tqdm(total=self.total, initial=self.frames, unit="frame", unit_scale=True, dynamic_ncols=True,
                            file=stream, desc=name or None)

    def rate(self) -> float:
        """Frames per second since this process started counting."""
        return (self.frames - self.start_frames) / max(self.clock() - self.t0, 1e-9)

    def advance(self, n: int) -> None:
        """``n`` more frames (every env step calls this with its batch size)."""
        self.frames += int(n)
        if self.bar is not None:
            self.bar.update(int(n))
        elif self.every_s > 0 and self.clock() >= self.next_line:
            self.next_line = self.clock() + self.every_s
            log.info("%s", self.line())

    def update(self, n: int) -> None:
        """tqdm's name for :meth:`advance`, so the loop can hold either."""
        self.advance(n)

    def batch_done(self, frames: int, last_eval: Mapping[str, float] | None = None,
                   last_eval_frames: int | None = None) -> None:
        """End of a collector batch: ``frames`` is the loop's own count (it wins over the sum of the
        steps); ``last_eval``: the metrics of its last evaluation, made at ``last_eval_frames``."""
        self.frames = int(frames)
        if last_eval:
            self.last_eval = {k: float(last_eval[k]) for k in SHOWN if k in last_eval}
            self.last_eval_frames = None if last_eval_frames is None else int(last_eval_frames)
        if self.bar is not None:
            self.bar.n = self.frames
            post = {"fps": f"{self.rate():.0f}", **{k: f"{v:.3f}" for k, v in self.last_eval.items()}}
            self.bar.set_postfix(post, refresh=True)

    def line(self) -> str:
        """The progress line: frames, frames/s, ETA and the last evaluation's metrics."""
        rate = self.rate()
        left = max(self.total - self.frames, 0)
        eta = format_duration(left / rate) if rate > 0 else "unknown"
        out = (f"{self.name + ': ' if self.name else ''}{self.frames:,} / {self.total:,} frames "
               f"({100 * self.frames / max(self.total, 1):.1f}%), {rate:,.0f} frames/s, ETA {eta}")
        if self.last_eval:
            at = f" at {self.last_eval_frames:,}" if self.last_eval_frames is not None else ""
            out += f"; last evaluation{at}: " + " ".join(f"{k} {v:.3f}" for k, v in self.last_eval.items())
        return out

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        elif self.every_s > 0 and self.frames > self.start_frames:
            log.info("%s", self.line())


def progress_for(cfg: Any, tr: Any, initial: int) -> Progress:
    """The training loop's :class:`Progress`: ``trainer.progress_bar`` and ``trainer.progress_every_s``
    of the run ``cfg`` (named by its method and seed), from ``initial`` frames."""
    method = getattr(getattr(cfg, "experiment", None), "method", None) or cfg.name
    return Progress(tr.total_frames, initial, name=f"{method} seed{cfg.seed}", bar=tr.progress_bar,
                    every_s=tr.progress_every_s, first_s=tr.progress_first_s)


class EpisodeProgress:
    """An evaluation's progress, called after every env step of its rollout (``on_step``): a line
    ``first_s`` after it starts, then every ``every_s``, with the step, the episodes done of
    ``episodes`` and what ``extra()`` adds (the advisor's rows asked); and the stop, checked at
    every step (``stop.check()`` raises when one was asked).

    Args:
        name: what the lines call the evaluation.
        episodes: the episodes it flies (one per scenario).
        every_s, first_s: as :class:`Progress`'s (0: no lines).
        stop: a :class:`uavlae.lifecycle.GracefulStop` (None: none checked).
        extra: a callable giving more of the line, or None.
        clock: seconds, for the tests.
    """

    def __init__(self, name: str, episodes: int, *, every_s: float, first_s: float | None = None, stop: Any = None,
                 extra: Any = None, clock: Any = time.monotonic):
        self.name, self.episodes, self.every_s, self.stop, self.extra = name, int(episodes), float(every_s), stop, extra
        self.clock = clock
        self.t0 = clock()
        self.next_line = self.t0 + min(self.every_s, self.every_s if first_s is None else float(first_s))
        self.lines = 0

    def __call__(self, step: int, finished: Any, next_td: Any = None) -> None:
        if self.stop is not None:
            self.stop.check()
        if self.every_s > 0 and self.clock() >= self.next_line:
            self.next_line = self.clock() + self.every_s
            self.lines += 1
            log.info("%s", self.line(step, int(finished.sum())))

    def line(self, step: int, done: int) -> str:
        out = (f"{self.name}: step {step}, {done} of {self.episodes} episodes done, "
               f"{format_duration(self.clock() - self.t0)}")
        more = self.extra() if self.extra is not None else ""
        return out + (f"; {more}" if more else "")

"""Progress: a bar that moves with every env step on a terminal; elsewhere a line at the stated
interval with frames, frames/s, ETA and the last evaluation's metrics (numbers by hand)."""

from __future__ import annotations

import io
import logging

from uavlae.progress import Progress, format_duration


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_durations_by_hand():
    assert format_duration(42.4) == "42s" and format_duration(300) == "5m00s" and format_duration(3725) == "1h02m"
    assert format_duration(-3) == "0s"


def test_lines_at_the_stated_interval_with_rate_eta_and_the_last_evaluation(caplog):
    clock = Clock()
    p = Progress(1000, initial=200, name="sac seed0", bar=True, every_s=60, stream=io.StringIO(), clock=clock)
    assert p.bar is None  # not a terminal: lines instead
    with caplog.at_level(logging.INFO, logger="uavlae.progress"):
        clock.t += 30
        p.advance(100)  # 30 s: before the interval, no line
        assert caplog.messages == []
        p.batch_done(300, {"DCR": 0.25, "CR": 0.5, "SLR": 0.0, "RVR": 0.1}, 256)
        clock.t += 30
        p.advance(100)  # 60 s, 200 frames since the start: 3.33 frames/s, 600 left: 180 s
        assert caplog.messages == [
            "sac seed0: 400 / 1,000 frames (40.0%), 3 frames/s, ETA 3m00s; "
            "last evaluation at 256: DCR 0.250 CR 0.500 SLR 0.000"]
        clock.t += 10
        p.advance(100)  # 10 s after the last line: none
        assert len(caplog.messages) == 1
        p.close()  # the closing line
        assert caplog.messages[-1].startswith("sac seed0: 500 / 1,000 frames (50.0%)")
    quiet = Progress(1000, bar=False, every_s=0, clock=clock)
    with caplog.at_level(logging.INFO, logger="uavlae.progress"):
        clock.t += 1000
        quiet.advance(10)
        quiet.close()
    assert len(caplog.messages) == 2  # every_s=0: no line at all


def test_a_bar_on_a_terminal_moves_with_each_update_and_shows_the_last_evaluation():
    term = Terminal()
    p = Progress(64, name="t", bar=True, stream=term)
    seen = []
    for _ in range(8):  # the training loop's calls, one per env step of 4 rows
        p.update(4)
        seen.append(p.bar.n)
    assert seen == [4, 8, 12, 16, 20, 24, 28, 32]
    p.batch_done(32, {"DCR": 0.5})
    assert p.bar.postfix.endswith("DCR=0.500")
    p.close()
    assert "32.0/64.0" in term.getvalue()  # the bar as drawn at the end of the batch


def test_a_training_run_reports_within_its_batches(tmp_path, caplog):
    """Off-policy training: the loop advances the progress by every env step, so with a line per
    step the frames of a 32-frame batch show 4 at a time."""
    from tests.test_train import _run

    with caplog.at_level(logging.INFO, logger="uavlae.progress"):
        final = _run("sac", tmp_path / "r", "trainer.progress_every_s=0.000001", "trainer.eval_every_frames=0")
    frames = [int(m.split(": ", 1)[1].split(" / ")[0].replace(",", "")) for m in caplog.messages if "sac seed0: " in m]
    assert frames[:9] == [4, 8, 12, 16, 20, 24, 28, 32, 36] and frames[-1] == final["frames"] == 128
    training = [m for m in caplog.messages if "sac seed0: " in m]
    assert "last evaluation at 128: DCR" in training[-1]
    # the evaluations after training report too: the actor's, then each baseline's, by its steps
    assert any(m.startswith("sac @ 128 frames: step 1, ") for m in caplog.messages)
    assert caplog.messages[-1].startswith("random: step ") and "of 2 episodes done" in caplog.messages[-1]


def test_the_first_line_comes_first_s_after_the_start_then_every_every_s(caplog):
    clock = Clock()
    p = Progress(1000, name="r", bar=False, every_s=60, first_s=10, clock=clock)
    seen = []
    with caplog.at_level(logging.INFO, logger="uavlae.progress"):
        for t in (5, 10, 30, 69, 70, 131):  # seconds since the start: lines at 10, 70 and 131
            clock.t = 100.0 + t
            p.advance(10)
            seen.append(len(caplog.messages))
    assert seen == [0, 1, 1, 1, 2, 3]
    assert Progress(10, bar=False, every_s=5, first_s=10, clock=clock).next_line == clock.t + 5  # never after every_s


def test_an_evaluation_reports_its_episodes_and_ends_at_a_stop(caplog):
    import os
    import signal

    import pytest
    import torch

    from uavlae.lifecycle import GracefulStop, StopRequested
    from uavlae.progress import EpisodeProgress

    clock = Clock()
    asked = {"n": 3}
    with GracefulStop() as stop, caplog.at_level(logging.INFO, logger="uavlae.progress"):
        ev = EpisodeProgress("sac with its advisor", 4, every_s=60, first_s=0, stop=stop, clock=clock,
                             extra=lambda: f"advisor asked for {asked['n']} rows of 64")
        clock.t += 95
        ev(12, torch.tensor([True, False, True, False]))
        assert caplog.messages == ["sac with its advisor: step 12, 2 of 4 episodes done, 1m35s; "
                                   "advisor asked for 3 rows of 64"]
        clock.t += 30
        ev(13, torch.tensor([True, True, True, False]))  # within the interval: no line
        assert len(caplog.messages) == 1
        os.kill(os.getpid(), signal.SIGTERM)  # the stop, as a scheduler sends it
        with pytest.raises(StopRequested) as err:
            ev(14, torch.tensor([True, True, True, False]))
    assert err.value.signum == signal.SIGTERM

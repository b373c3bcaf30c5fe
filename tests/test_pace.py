"""Equal budgets in samples on a shared GPU (imac_model/training/pace.py): a paced run waits for the run it
follows, goes on when that run catches up, stops at its final count, and is freed when it dies."""

from __future__ import annotations

import threading
import time

import pytest

from imac_data.errors import InputError
from imac_model.training.pace import Pace, read_progress, report_progress


def test_a_progress_file_round_trips_and_a_damaged_one_is_named(tmp_path):
    path = tmp_path / "runs" / "motion_contact.json"
    assert read_progress(path) is None  # not written yet
    report_progress(path, 512)
    assert read_progress(path) == {"samples": 512, "done": False}
    report_progress(path, 1024, done=True)
    assert read_progress(path) == {"samples": 1024, "done": True} and not list(path.parent.glob("*.tmp"))
    path.write_text("{")
    with pytest.raises(InputError, match="motion_contact.json: unreadable progress file"):
        read_progress(path)
    path.write_text('{"samples": 3}')
    with pytest.raises(InputError, match="holds 'samples' and 'done'"):
        read_progress(path)


def test_a_paced_run_steps_while_level_and_stops_at_the_count_of_a_finished_run(tmp_path):
    theirs = tmp_path / "theirs.json"
    pace = Pace(theirs, poll_s=0.01)
    report_progress(theirs, 32)
    soon = time.time() + 5.0
    assert pace.may_step(0, soon) and pace.may_step(32, soon)  # level: one more step may go ahead
    report_progress(theirs, 32, done=True)
    assert pace.may_step(16, soon) and not pace.may_step(32, soon)
    assert pace.waited_s < 1.0 and pace.freed is None


def test_a_paced_run_waits_for_the_other_to_catch_up_and_no_longer_than_its_deadline(tmp_path):
    theirs = tmp_path / "theirs.json"
    report_progress(theirs, 16)
    pace = Pace(theirs, poll_s=0.01)
    catch_up = threading.Timer(0.3, report_progress, (theirs, 48))
    catch_up.start()
    t0 = time.time()
    assert pace.may_step(32, t0 + 5.0)  # ahead by 16: it waits until the other has 48
    assert 0.25 <= time.time() - t0 < 3.0 and pace.waited_s >= 0.25
    catch_up.join()
    t0 = time.time()
    assert not pace.may_step(64, t0 + 0.3)  # ahead, and the other never comes: the deadline ends it
    assert 0.25 <= time.time() - t0 < 3.0


def test_a_run_that_stops_reporting_frees_the_run_it_paced(tmp_path):
    theirs = tmp_path / "theirs.json"
    report_progress(theirs, 0)
    pace = Pace(theirs, stale_s=0.3, poll_s=0.01)
    t0 = time.time()
    assert pace.may_step(16, t0 + 10.0) and pace.freed == "stale" and 0.25 <= time.time() - t0 < 3.0
    assert pace.may_step(10_000, t0 + 10.0)  # freed for good
    assert Pace(tmp_path / "never.json", stale_s=0.2, poll_s=0.01).may_step(16, time.time() + 10.0)  # never began

"""Progress in a batch job: log lines when output is not a terminal."""

import logging

from acoustlab.core.progress import progress


def test_progress_logs_when_not_a_terminal(caplog):
    caplog.set_level(logging.INFO, logger="acoustlab.progress")
    assert list(progress(range(4), desc="simulate forest", unit="chunk", interval_s=0.0)) == [0, 1, 2, 3]
    lines = [r.message for r in caplog.records]
    assert lines[0].startswith("simulate forest: 1/4 chunks (") and "left" in lines[0]
    assert lines[-1].startswith("simulate forest: 4 chunks done in")


def test_progress_is_quiet_for_short_stages(caplog):
    caplog.set_level(logging.INFO, logger="acoustlab.progress")
    assert list(progress(iter("abc"), desc="features")) == ["a", "b", "c"]  # a generator without a length works too
    assert not caplog.records

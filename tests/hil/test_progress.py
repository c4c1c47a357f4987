import dataclasses

from hil.logs.records import TimingRecord
from hil.progress import campaign_line, tick_line
from tests.hil.logs.synthetic_log import make_trial


def test_tick_line_shows_phase_range_error_age_frames_and_period():
    trial = make_trial(seed=51, rate_hz=10.0)
    tick = trial.ticks[100]
    line = tick_line(tick)
    error_mm = 1000 * trial.errors["fused"][0][100]
    assert line.startswith(f"t  10.0 s  approach  range {tick.range_m:.3f} m  fused error")
    assert f"fused error {error_mm:5.1f} mm" in line
    assert f"age {tick.estimate.age_s:.2f} s" in line
    assert f"frames {tick.vision.frames_received} ({tick.vision.frames_dropped} dropped)" in line
    assert f"period {tick.timing.period_ms:.1f} ms" in line and "DEADLINE" not in line
    idle = tick_line(trial.ticks[0])
    assert "range   –" in idle and "estimate uninitialized" in idle and "period" not in idle
    late = dataclasses.replace(tick, truth=None, timing=TimingRecord(31.0, 21.0, 1.0, True))
    assert "estimate ok" in tick_line(late) and tick_line(late).endswith("DEADLINE MISS")


def test_campaign_line_counts_trials_and_projects_the_rest_at_the_mean_so_far():
    line = campaign_line("matrix/2.0-none-s0-ab12", 41.4, 12, 67, 480.0)
    # 480 s for 12 trials: 40 s each, 55 to go → 2200 s ≈ 37 min
    assert line == "[12/67] matrix/2.0-none-s0-ab12 41 s; 8 min elapsed, ETA 37 min"
    assert campaign_line("k", 5.0, 1, 3, 5.0) == "[1/3] k 5 s; 5 s elapsed, ETA 10 s"
    assert campaign_line("k", 5.0, 3, 3, 15.0).endswith("ETA 0 s")

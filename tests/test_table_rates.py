"""`bench/table_rates.py`: which measured rate `snac table --dry-run` estimates from."""

from bench.table_rates import calibrated, idle_reference, merged

IDLE_ONE_SEED = {"steps_per_s": 72_000, "seeds": 1, "source": "a results page"}
RATES = {
    "ppo": {
        "1d-static-sin": IDLE_ONE_SEED,
        "2d-static-dense": {"steps_per_s": 9_000, "seeds": 3, "load_avg": [2.0, 2.1]},
    },
    "sac": {"1d-static-sin": {"steps_per_s": 80_000}},  # entries before seeds were recorded: one seed
}
MEASURED = {"wall_steps_per_s": 10_000, "cpu_steps_per_s": 6_000, "seeds": 3, "load_avg": [1.5, 1.6], "measured": "m"}


def test_an_idle_rate_calibrates_only_a_measurement_with_its_seed_count():
    assert idle_reference(RATES, "ppo", "1d-static-sin", seeds=1) is IDLE_ONE_SEED
    assert idle_reference(RATES, "ppo", "1d-static-sin", seeds=3) is None
    assert idle_reference(RATES, "sac", "1d-static-sin", seeds=1) == {"steps_per_s": 80_000}


def test_a_loaded_or_missing_entry_calibrates_nothing():
    assert idle_reference(RATES, "ppo", "2d-static-dense", seeds=3) is None  # measured under load
    assert idle_reference(RATES, "ppo", "3d-static-dense", seeds=1) is None
    assert idle_reference(RATES, "dqn", "1d-static-sin", seeds=1) is None


def test_calibration_scales_the_cpu_rate_by_the_reference_cores_in_use():
    # The reference kept 72,000 / 40,000 = 1.8 cores busy when idle: 6,000 x 1.8 = 10,800.
    reference = {"idle_steps_per_s": 72_000, "cpu_steps_per_s": 40_000}
    assert calibrated(MEASURED, reference, "1d-static-sin")["steps_per_s"] == 10_800
    assert calibrated(MEASURED, None, "1d-static-sin", cores=2)["steps_per_s"] == 12_000
    entry = calibrated(MEASURED, None, "1d-static-sin")
    assert entry["steps_per_s"] == 10_000 and "load average [1.5, 1.6]" in entry["source"]
    assert "steps_per_s" not in MEASURED  # the measured entry is not changed in place


def test_every_committed_rate_is_positive_and_names_where_it_came_from():
    from agents.table.rates import load_rates

    for algorithm, tasks in load_rates().items():
        for task, entry in tasks.items():
            assert entry["steps_per_s"] > 0 and entry.get("seeds", 1) >= 1 and entry["source"], (algorithm, task)


def test_writing_keeps_an_idle_rate_and_an_evaluation_time_measured_before():
    idle = {"steps_per_s": 72_000, "seeds": 3, "source": "a results page", "eval_s": 5.0}
    loaded = {"steps_per_s": 9_000, "seeds": 3, "load_avg": [2.0, 2.1], "source": "s", "eval_s": 15.0}
    fresh = {"steps_per_s": 12_000, "seeds": 3, "load_avg": [1.6, 1.6], "source": "t"}
    assert merged(idle, {**fresh, "eval_s": 4.0}) == {**idle, "eval_s": 4.0}  # idle rate kept, new protocol time
    assert merged(loaded, fresh) == {**fresh, "eval_s": 15.0}  # new rate, earlier protocol time
    assert merged(loaded, {**fresh, "eval_s": 12.0})["eval_s"] == 12.0
    assert merged({}, fresh) == fresh
    one_seed = {**idle, "seeds": 1}  # another seed count: the new measurement replaces it
    assert merged(one_seed, fresh) == {**fresh, "eval_s": 5.0}

"""Designs (SPEC §7): fixed ones equal designs.json; samplers obey the size rules."""

import jax
import numpy as np
import pytest
from scipy.stats import norm

from snac_jax import TASKS, make, test_design_names
from snac_jax.designs import TRIANGLE_COUNT_RANGE, reference_designs, sample_design, sine_curve

DATA = reference_designs()
STATIC = [t for t in TASKS if "static" in t]
DYNAMIC = [t for t in TASKS if "dynamic" in t]


@pytest.mark.parametrize("task", STATIC)
def test_static_designs_equal_reference_data(task):
    env, params = make(task)
    ref = DATA[task]
    np.testing.assert_array_equal(np.asarray(params.designs[0]).reshape(np.shape(ref["design"])), ref["design"])
    assert int(params.design_max_bricks[0]) == ref["max_bricks"]
    assert int(params.max_steps_in_episode) == ref["max_steps"]


@pytest.mark.parametrize("task", DYNAMIC)
@pytest.mark.parametrize("index", range(10))
def test_test_designs_equal_reference_data(task, index):
    env, params = make(task, test_design=index)
    ref = DATA[test_design_names(task)[index]]
    np.testing.assert_array_equal(np.asarray(params.designs[0]).reshape(np.shape(ref["design"])), ref["design"])
    assert int(params.design_max_bricks[0]) == ref["max_bricks"]
    assert int(params.max_steps_in_episode) == ref["max_steps"]


def test_1d_static_shapes_follow_their_formulas():
    x = np.arange(30)
    np.testing.assert_array_equal(np.round(10 * np.sin(2 * np.pi * x / 30) + 20), DATA["1d-static-sin"]["design"])
    gauss = np.round(100 * norm.pdf(np.linspace(-18, 18, 30), 0, 3) + 17)
    np.testing.assert_array_equal(gauss, DATA["1d-static-gauss"]["design"])
    step = np.where((x // 5) % 2 == 0, 25, 15)
    np.testing.assert_array_equal(step, DATA["1d-static-step"]["design"])


SINE_TEST_PARAMS = [
    (3, 1, -np.pi),
    (4, 2, -np.pi / 2),
    (5, 3, -np.pi / 2),
    (6, 1, np.pi),
    (7, 2, -np.pi),
    (7, 3, -np.pi / 2),
    (8, 1, np.pi / 2),
    (9, 2, np.pi),
    (10, 3, -np.pi),
    (11, 1, -np.pi / 2),
]


@pytest.mark.parametrize("index", range(10))
def test_1d_sine_generator_reproduces_test_curves(index):
    amplitude, frequency, phase = SINE_TEST_PARAMS[index]
    curve = np.asarray(sine_curve(amplitude, frequency, phase))
    np.testing.assert_array_equal(curve.reshape(-1), DATA[f"1d-dynamic-test{index}"]["design"])


@pytest.mark.slow
@pytest.mark.parametrize("task", ["2d-dynamic-dense", "2d-dynamic-sparse", "3d-dynamic-dense", "3d-dynamic-sparse"])
def test_sampled_triangles_obey_size_rules(task):
    env, params = make(task, design_bank_size=512, design_seed=3)
    bank = np.asarray(params.designs)
    dim = env.config.dim
    density = task.rsplit("-", 1)[1]
    low, high = TRIANGLE_COUNT_RANGE[(dim, density)]
    counts = (bank > 0).sum(axis=(1, 2))
    assert bank.shape == (512, 20, 20)
    assert np.all(counts > low)
    if high is not None:
        assert np.all(counts < high)
    assert set(np.unique(bank)) <= {0, 6 if dim == 3 else 1}
    np.testing.assert_array_equal(
        params.design_max_bricks, bank.sum(axis=(1, 2)) if dim == 3 else np.maximum(counts, 30)
    )
    assert len({b.tobytes() for b in bank}) > 400  # a bank of distinct designs, not one repeated


@pytest.mark.slow
def test_sparse_triangles_are_outlines_and_dense_are_filled():
    _, sparse = make("2d-dynamic-sparse", design_bank_size=64)
    _, dense = make("2d-dynamic-dense", design_bank_size=64)
    # An outline has no cell whose four neighbours are all in the design (no interior).
    for design in np.asarray(sparse.designs):
        padded = np.pad(design, 1)
        interior = design & padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
        assert interior.sum() <= 2  # thick diagonal joints of digital lines at most
    # Filled triangles have interiors.
    assert np.mean([np.asarray(d)[1:-1, 1:-1].sum() > 0 for d in dense.designs]) == 1.0


def test_sine_bank_in_range_and_varied():
    _, params = make("1d-dynamic", design_bank_size=256)
    bank = np.asarray(params.designs)[:, 0, :]
    assert bank.shape == (256, 30)
    assert bank.min() >= 20 - 12 and bank.max() <= 20 + 12
    amplitude = (bank.max(axis=1) - bank.min(axis=1)) / 2
    assert amplitude.min() >= 2 and amplitude.max() <= 12.5
    assert len({b.tobytes() for b in bank}) > 200


def test_reset_draws_designs_from_the_bank():
    env, params = make("2d-dynamic-dense", design_bank_size=8)
    keys = jax.random.split(jax.random.key(0), 64)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    drawn = {np.asarray(d).tobytes() for d in states.design}
    bank = {np.asarray(d).tobytes() for d in params.designs}
    assert drawn <= bank and len(drawn) >= 6


@pytest.mark.parametrize("task", DYNAMIC)
def test_training_banks_exclude_every_test_design(task):
    """The default bank (the one training uses) and another seed's: no design equals a test design."""
    tests = np.stack(
        [
            np.asarray(DATA[name]["design"]).reshape(np.shape(make(task, test_design=0)[1].designs[0]))
            for name in test_design_names(task)
        ]
    )
    for options in ({}, {"design_bank_size": 512, "design_seed": 7}):
        _, params = make(task, **options)
        bank = np.asarray(params.designs)
        equal = np.all(bank[:, None] == tests[None], axis=(2, 3))
        assert not equal.any(), (
            f"{task} {options}: bank designs {np.flatnonzero(equal.any(axis=1))[:5]} are test designs"
        )


@pytest.mark.slow
def test_an_excluded_draw_is_redrawn_and_the_others_kept():
    keys = jax.random.split(jax.random.key(3), 4)
    plain = np.asarray(jax.vmap(lambda k: sample_design(k, 1, None))(keys))
    excluded = plain[[1, 3]]
    redrawn = np.asarray(jax.jit(jax.vmap(lambda k: sample_design(k, 1, None, excluded)))(keys))
    np.testing.assert_array_equal(redrawn[[0, 2]], plain[[0, 2]])
    for design in redrawn[[1, 3]]:
        assert not np.any(np.all(design[None] == excluded, axis=(1, 2)))

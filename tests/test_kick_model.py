"""The contextual kick (a family of kicks given at knots) and the roughness of a family of kicks,
against hand computations; pure numbers, no physics."""

import numpy as np
import pytest

from bumps_jax.tasks.kick import keyframes as kick_model


def _knot_params():
    """Three in-bounds kicks: the middle of the bounds, and two moved from it by whole scale units."""
    base = (kick_model.PARAM_LOW + kick_model.PARAM_HIGH) / 2
    return np.stack([base, base - kick_model.PARAM_SCALE, base + 2 * kick_model.PARAM_SCALE])


def test_the_contextual_kick_is_its_knot_values_at_the_knots_and_linear_between():
    knots = kick_model.knot_targets(8.0, 16.0, 3)
    np.testing.assert_allclose(knots, [8.0, 12.0, 16.0])
    params = _knot_params()
    for k, target in enumerate(knots):
        np.testing.assert_allclose(kick_model.family_params(params, knots, target), params[k], rtol=1e-6)
    # A quarter of the way from 12 to 16 m: three quarters of the 12 m kick, a quarter of the 16 m one.
    np.testing.assert_allclose(kick_model.family_params(params, knots, 13.0), 0.75 * params[1] + 0.25 * params[2],
                               rtol=1e-5)  # fmt: skip
    # Outside the knots the end kicks hold; the result is clipped into the bounds.
    np.testing.assert_allclose(kick_model.family_params(params, knots, 7.0), params[0], rtol=1e-6)
    far = params.copy()
    far[2, 0] = 100.0
    assert float(kick_model.family_params(far, knots, 16.0)[0]) == kick_model.PARAM_HIGH[0]
    with pytest.raises(ValueError, match="n_knots >= 2"):
        kick_model.knot_targets(8.0, 16.0, 1)
    with pytest.raises(ValueError, match="low < high"):
        kick_model.knot_targets(16.0, 8.0, 3)


def test_largest_jump_by_hand():
    """Targets given out of order; jumps are taken between neighbours in distance, in scale units."""
    base = np.asarray(kick_model.DEFAULT_PARAMS, np.float64)
    kicks = np.stack([base, base, base])
    kicks[1, kick_model.PARAM_NAMES.index("back_knee")] += 12.0  # 12 / 8 = 1.5 units from the 10 m kick
    kicks[2, kick_model.PARAM_NAMES.index("t_swing")] += 0.06  # 0.06 / 0.03 = 2 units from the 12 m kick
    targets = [10.0, 12.0, 14.0]
    order = [2, 0, 1]
    out = kick_model.largest_jump(kicks[order], np.asarray(targets)[order])
    # 12 -> 14 m: t_swing 2 units, back_knee 1.5 units (it drops back to the base).
    assert out["param"] == "t_swing" and out["between_m"] == [12.0, 14.0]
    assert out["jump"] == pytest.approx(2.0)
    kicks[2, kick_model.PARAM_NAMES.index("t_swing")] = base[kick_model.PARAM_NAMES.index("t_swing")]
    out = kick_model.largest_jump(kicks, targets)
    assert out == {"jump": pytest.approx(1.5), "param": "back_knee", "between_m": [10.0, 12.0]}
    with pytest.raises(ValueError, match="T >= 2"):
        kick_model.largest_jump(kicks[:1], targets[:1])

"""The roughness of a family of kicks, against hand computations; pure numbers, no physics."""

import numpy as np
import pytest

from bumps_jax.tasks.kick import keyframes as kick_model


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

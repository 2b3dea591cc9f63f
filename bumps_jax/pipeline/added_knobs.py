"""The config keys added after runs were made, each with its value before it existed.

A stage manifest written before a knob existed lacks it; such a run is the same run as one with
the knob at the value given here (the value that behaves as the code did before the knob), so it
resumes (`pipeline.check_manifest`). At any other value, a preset's default included, the stage is
stale. The validation names these values as the ones that turn a knob off.
"""

ADDED_KNOBS = {
    "experts.tune.start_leash": 0.0,
    "experts.tune.neighbour_leash": 0.0,
    "experts.tune.midpoint_weight": 0.0,
    "experts.tune.restarts": 1,
    "experts.tune.batch_restarts": False,
    "meta.trainer": "separate",
    "meta.inputs": "unit",
    "experts.tune.keep": "run",
    "experts.tune.polish_generations": 0,
    "experts.tune.polish_sigma": 2.0,
    "experts.bc.common_start": "main",
    "experts.bc.common_start_strength": False,
    "experts.ppo.unroll_gae": False,
    "baseline.ppo.unroll_gae": False,
    "meta.train.unroll": 1,
}

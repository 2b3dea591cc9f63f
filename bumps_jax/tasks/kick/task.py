"""The kick as a BUMPS task: its env, its experts' start, its own prior stage and its report."""

from bumps_jax.report import tables
from bumps_jax.tasks.kick import config, env, policies
from bumps_jax.tasks.kick.start import KeyframeStart
from bumps_jax.tasks.protocol import Report, Task

TASK = Task(
    name="kick",
    env_class=env.KickEnv,
    stages=("prior", "experts", "meta", "filter", "heldout", "baseline"),
    config=config,
    own_stages={"prior": "bumps_jax.tasks.kick.prior"},
    expert_start=KeyframeStart(),
    normalise_meta_inputs=False,  # (phase, normalised target) are in [0, 1] already
    report=Report(
        experts=tables.experts_markdown,
        table1=lambda rows, unit: tables.table1_markdown(rows),
        table2=lambda rows, unit: tables.table2_markdown(rows),
        axes=("target distance (m)", "mean final error (m)", "achieved distance (m)"),
        paper_rows=True,
        start_row="starting_kicks",
        ship_policies=policies.write,
    ),
)

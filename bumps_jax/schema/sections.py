"""The stages' config sections at their defaults (the paper's sizes): what every task's tree holds.

A task's `config.sections()` builds its tree from these, giving its own contexts and sizes and
adding the sections and keys its plug-ins read (the kick's prior, its experts' starting kicks).
Each leaf's comment says what it does.
"""

from __future__ import annotations

import ml_collections
from ml_collections import FieldReference

from bumps_jax.algo import ppo_config
from bumps_jax.schema import validation


def experts(tasks) -> ml_collections.ConfigDict:
    """One PPO expert per training context."""
    cfg = ml_collections.ConfigDict()
    cfg.tasks = tuple(tasks)  # the training contexts, one expert each
    cfg.seed = 0  # the experts' PPO seed
    cfg.updates_per_chunk = 25  # speed and logging only: PPO updates per compiled chunk
    cfg.keep_checkpoints = 3  # checkpoints kept while training (disk only)
    cfg.ppo = ppo_config.default_config()  # PPO's hyperparameters and budget per expert
    cfg.eval = ml_collections.ConfigDict()  # every expert on its own context
    cfg.eval.repetitions = 100  # noisy episodes per expert
    cfg.eval.seed = 1  # noise of that evaluation
    return cfg


def family() -> ml_collections.ConfigDict:
    """`experts.family`, for a task without its own expert start: the experts as one family."""
    cfg = ml_collections.ConfigDict()
    # PPO updates of the centre expert (the context nearest the contexts' mean) alone, before
    # every expert continues from it; 0: every expert starts from its own fresh policy.
    cfg.centre_updates = 0
    cfg.ramp_updates = 0  # updates over which each expert's target moves from the centre's context to its own
    # Centre experts trained side by side (seeds of their own) before one is chosen: upright where
    # the env reports a posture, then the lowest error on the centre context (`choose_centre`).
    cfg.candidates = 1
    # PPO updates the candidates train side by side before the choice; the chosen one then goes
    # on alone to centre_updates (0: the choice after all of them).
    cfg.choose_after = 0
    # Rounds of fresh candidates at most: the next round is drawn only when every candidate of
    # the last one runs flipped (the env's posture check); 1: one round, whatever its posture.
    cfg.rounds = 1
    return cfg


def equal_budget(experts: ml_collections.ConfigDict, episode_steps: int, per_update: int) -> int:
    """The baseline's env steps per seed for a cost equal to one run's experts' (`experts_env_steps`):
    the nearest whole number of its updates of `per_update` steps each."""
    return max(1, round(experts_env_steps(experts, episode_steps) / per_update)) * per_update


def chunk_size(updates: int, most: int) -> int:
    """The largest number of updates, at most `most`, that divides `updates` (a compiled chunk)."""
    return max(d for d in range(1, most + 1) if updates % d == 0)


def choice_update(family: ml_collections.ConfigDict) -> int:
    """After how many of the centre's updates its candidates are compared (`choose_after`; 0:
    after all of them)."""
    n = int(family.centre_updates)
    return min(int(family.get("choose_after", 0)) or n, n)


def centre_env_updates(family: ml_collections.ConfigDict, rounds: int = 1) -> int:
    """PPO updates of the family's centre phase, every candidate's counted: the candidates' side
    by side until the choice (in each of `rounds` rounds), then the chosen one's alone."""
    n, m = int(family.centre_updates), choice_update(family)
    return rounds * int(family.get("candidates", 1)) * m + (n - m)


def experts_env_steps(experts: ml_collections.ConfigDict, episode_steps: int) -> int:
    """Env steps of one run's experts together: every expert's PPO and the family's centre
    candidates' of one round (the budget a baseline of the same cost gets per seed; a run that
    draws another round spends more, and its record says so)."""
    centre = centre_env_updates(experts.family) * experts.ppo.num_envs * episode_steps
    return len(experts.tasks) * experts.ppo.total_env_steps + centre


def meta(eval_tasks) -> ml_collections.ConfigDict:
    """Behaviour cloning into the contextual meta-policies, and their unfiltered evaluation."""
    cfg = ml_collections.ConfigDict()
    # name -> (hidden layers, width): the paper's two meta-policies.
    cfg.nets = ml_collections.ConfigDict({"meta_4x256": (4, 256), "meta_11x128": (11, 128)})
    cfg.dataset = ml_collections.ConfigDict()  # the experts' rollouts the nets are cloned from
    cfg.dataset.repetitions = 1  # rollouts per expert; 1 records them noise-free (the paper)
    cfg.dataset.seed = 0  # noise of those rollouts (with repetitions > 1)
    # Closed-loop cloning. DART: the recorded episodes act with the expert's action plus Gaussian
    # noise of this std (labels stay the expert's own action); 0: the expert's action.
    cfg.dataset.action_noise = 0.0
    cfg.dataset.clip_labels = False  # labels clipped to the env's action bound (`ACTION_BOUND`)
    cfg.train = ml_collections.ConfigDict()  # behaviour cloning (`bc.make_trainer`: every net in one program)
    cfg.train.learning_rate = 3e-4  # Adam, times decay_rate every decay_every epochs
    cfg.train.decay_rate = 0.8  # factor on the rate every decay_every epochs
    cfg.train.decay_every = 5000  # epochs
    cfg.train.batch_size = 128  # pairs per gradient step
    cfg.train.epochs = 150_000  # passes over the dataset
    cfg.train.chunk = 2500  # speed and logging only: epochs per host sync (progress, CSV, checkpoint)
    cfg.train.n_seeds = 1  # initialisations trained side by side; seed 0 is the table's row
    cfg.train.seed = 0  # initialisation and shuffling seed
    cfg.eval = ml_collections.ConfigDict()  # the unfiltered evaluation (Table 1)
    cfg.eval.tasks = tuple(eval_tasks)  # the test contexts
    cfg.eval.repetitions = 100  # noisy episodes per net per test context
    cfg.eval.seed = 1  # noise of that evaluation
    return cfg


def closed_loop_meta(eval_tasks, action_noise: float = 0.2, clip_labels: bool = True) -> ml_collections.ConfigDict:
    """`meta` for a policy that reads its state (closed loop), at a GPU's size: 8 recorded episodes
    per expert with reset noise, each acting with DART's `action_noise` (0: the expert's action)
    and labelled with the expert's action, clipped to the env's bound with `clip_labels`; 300
    epochs of Adam at 1e-3 on batches of 256 (x 0.8 every 50); 20 evaluation episodes a context."""
    cfg = meta(eval_tasks)
    cfg.dataset.repetitions = 8
    cfg.dataset.action_noise = action_noise
    cfg.dataset.clip_labels = clip_labels
    cfg.train.learning_rate = 1e-3
    cfg.train.batch_size = 256
    cfg.train.epochs = 300
    cfg.train.decay_every = 50
    cfg.train.chunk = 25
    cfg.eval.repetitions = 20
    return cfg


def filtering(tasks, context_range, context_step, high_context_step, width) -> ml_collections.ConfigDict:
    """Policy filtering over sampled contexts (Table 2)."""
    cfg = ml_collections.ConfigDict()
    cfg.tasks = tuple(tasks)  # the test contexts filtered (Table 2)
    cfg.context_range = tuple(context_range)  # sampled contexts form a grid over this range ...
    cfg.context_step = context_step  # ... of this step
    cfg.high_context_step = high_context_step  # the "high sample rate" variant's step
    cfg.width = width  # a test context's candidates are the contexts within +- width of it
    # "fixed": every candidate context gets `selection_repetitions` rollouts. "halving":
    # successive halving: every candidate gets halving_rungs[0] rollouts, each task's best
    # `halving_keep` fraction of its candidates goes on to the next rung's total, and so on; the
    # scores at a rung use all of a context's rollouts so far.
    cfg.selection = "halving"
    cfg.selection_repetitions = 10  # noisy rollouts per sampled context ("fixed")
    cfg.halving_rungs = (2, 8, 32, 100)  # rollouts per surviving context after each rung ("halving")
    cfg.halving_keep = 0.25  # fraction of a task's candidates that goes on to the next rung ("halving")
    cfg.eval_repetitions = 100  # fresh noisy rollouts of each task's chosen context
    cfg.seed = 0  # split into independent selection and evaluation noise
    cfg.net_seed = 0  # which initialisation of a meta-policy ensemble is filtered
    # Speed only: episodes per device per program call, one compiled program for every batch
    # (None: one call, and one compile, per batch size).
    cfg.block = FieldReference(4096, field_type=int)
    return cfg


def baseline(ppo: ml_collections.ConfigDict, eval_tasks, sample_task_range) -> ml_collections.ConfigDict:
    """The multi-task PPO baseline (the paper's Figure 1): one contextual policy for every context."""
    cfg = ml_collections.ConfigDict()
    cfg.seeds = 6  # independent runs, trained side by side
    cfg.updates_per_chunk = 25  # speed and logging only: PPO updates per compiled chunk
    cfg.keep_checkpoints = 3  # checkpoints kept while training (disk only)
    cfg.eval_tasks = tuple(eval_tasks)  # where each seed's policy is evaluated
    cfg.eval_repetitions = 100  # noisy episodes per test context
    cfg.eval_seed = 7  # noise of that evaluation
    cfg.ppo = ppo  # PPO's settings and budget per seed
    cfg.ppo.sample_task_range = tuple(sample_task_range)  # each episode draws its context from U[low, high]
    # A second arm: the same seeds at this policy learning rate, trained beside the first
    # (ppo.learning_rate) in one program; None: the first arm only.
    cfg.extra_learning_rate = FieldReference(1e-5, field_type=float)
    return cfg


def heldout(targets, seed: int) -> ml_collections.ConfigDict:
    """An evaluation on contexts no other stage uses (`evaluate --heldout`, or `--dev`)."""
    cfg = ml_collections.ConfigDict()
    cfg.targets = tuple(targets)  # the contexts evaluated
    cfg.seed = seed  # noise of these episodes (selection and fresh); no other section uses it
    cfg.repetitions = 100  # fresh noisy episodes per context and variant
    # Filtering a context: candidates are filter.context_range / context_step's grid and the
    # context itself within +- filter.width, each rolled out this many times on its own episodes.
    cfg.selection_repetitions = 10
    return cfg


def equal_budget_derived(contacts_per_episode: int, most_chunk: int) -> tuple:
    """A task's `DERIVED` (`config.derive`) where the baseline costs what one run's experts cost:
    an update rolls out every expert's batch, its budget per seed is the experts' whole in whole
    updates (`equal_budget`), in chunks of at most `most_chunk` updates that divide them, and
    Warp's contact pool holds the larger training program at `contacts_per_episode`."""

    def per_update(cfg) -> int:
        return cfg.baseline.ppo.num_envs * cfg.env.episode_steps

    def largest_program(cfg) -> int:  # episodes: the experts' together, or the baseline's seeds x arms
        return max(len(cfg.experts.tasks) * cfg.experts.ppo.num_envs, validation.baseline_runs(cfg.baseline))

    return (
        ("baseline.ppo.num_envs", lambda cfg: len(cfg.experts.tasks) * cfg.experts.ppo.num_envs),
        ("baseline.ppo.total_env_steps", lambda cfg: equal_budget(cfg.experts, cfg.env.episode_steps, per_update(cfg))),
        (
            "baseline.updates_per_chunk",
            lambda cfg: chunk_size(cfg.baseline.ppo.total_env_steps // per_update(cfg), most_chunk),
        ),
        ("env.warp_contacts", lambda cfg: contacts_per_episode * largest_program(cfg)),
    )

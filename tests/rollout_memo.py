"""A memo of rollout calls for tests whose code rolls out the same episodes more than once, and
the digest of inputs it keys them by."""

import hashlib

import jax
import jax.numpy as jnp
import numpy as np


class RolloutMemo:
    """Rollout calls (`filtering.run_blocked`, `meta.evaluate_unfiltered`: (grid, inputs...) ->
    dict of metrics), each run once per program and inputs. A call whose program and inputs
    (every array's bytes) equal an earlier call's gets copies of that call's metrics; any other
    call runs. `runs` and `hits` count the two."""

    def __init__(self):
        self.done, self.runs, self.hits = {}, 0, 0

    def wrap(self, fn):
        def memo(grid, *args, **kwargs):
            key = (id(grid), fn.__name__, digest((args, sorted(kwargs.items()))))
            if key in self.done:
                self.hits += 1
            else:
                self.runs += 1
                self.done[key] = (grid, fn(grid, *args, **kwargs))  # the grid kept: its id stays its own
            return {k: np.array(v) for k, v in self.done[key][1].items()}

        return memo

    def patch(self, mp, filtering=None, meta_stage=None):
        """With pytest's MonkeyPatch `mp`: the given modules' rollout calls through this memo."""
        if filtering is not None:
            mp.setattr(filtering, "run_blocked", self.wrap(filtering.run_blocked))
        if meta_stage is not None:
            mp.setattr(meta_stage, "evaluate_unfiltered", self.wrap(meta_stage.evaluate_unfiltered))


class EpisodeMemo(RolloutMemo):
    """RolloutMemo per episode, for `filtering.run_blocked` (grid, params, contexts (B,), targets
    (B,), keys (B,), *rest) -> dict of metrics (B, ...): a call each of whose episodes (its
    context, target and key, with the call's program, params and other arguments) some earlier
    call played gets those episodes' metrics; any other call runs whole. An episode's metrics do
    not depend on the other episodes of its call (each is its own world), so a call that asks for
    episodes played before, in whatever order or company, replays them without the physics."""

    def wrap(self, fn):
        def memo(grid, params, contexts, targets, keys, *rest, **kwargs):
            call = (id(grid), fn.__name__, digest((params, rest, sorted(kwargs.items()))))
            episodes = [(*call, digest((contexts[i], targets[i], keys[i]))) for i in range(len(contexts))]
            if all(e in self.done for e in episodes):
                self.hits += 1
            else:
                self.runs += 1
                m = fn(grid, params, contexts, targets, keys, *rest, **kwargs)
                for i, e in enumerate(episodes):  # the grid kept: its id stays its own
                    self.done[e] = (grid, {k: np.array(v[i]) for k, v in m.items()})
            return {k: np.stack([self.done[e][1][k] for e in episodes]) for k in self.done[episodes[0]][1]}

        return memo


def digest(tree) -> str:
    """A hash of every leaf's type, shape, dtype (and weak typing) and bytes (random keys by their
    key data)."""
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(tree):
        if isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        a = np.asarray(leaf)
        h.update(f"{type(leaf).__name__} {a.dtype} {getattr(leaf, 'weak_type', None)} {a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()

"""Run by test_runio.py as a child process: a behaviour-cloning run of many short chunks into
argv[1], which the test interrupts with SIGINT (as Ctrl-C or `timeout -s INT` would)."""

import sys

import numpy as np

from bumps_jax import config, resumable
from bumps_jax.algo import bc


def main(out_dir: str) -> None:
    cfg = config.make_config("tiny", {"meta.train.epochs": 10, "meta.train.chunk": 1, "meta.train.decay_every": 10})
    rng = np.random.default_rng(0)
    data = bc.Dataset(obs=rng.random((64, 2), np.float32), actions=rng.random((64, 22), np.float32),
                      task=np.zeros(64, np.float32))  # fmt: skip
    try:
        bc.train(bc.MetaPolicy(1, 8), data, cfg.meta.train, out_dir, say=lambda *a, **k: print(*a, flush=True))
    except resumable.Interrupted:
        sys.exit(f"interrupted: rerun the same command to resume {out_dir} from its last checkpoint")  # as cli.main
    print("finished", flush=True)


if __name__ == "__main__":
    main(sys.argv[1])

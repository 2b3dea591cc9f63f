"""The pipeline's stages, one module each, run by `bumps_jax.pipeline.runner`.

Every stage module has

    OUTPUT = "<record>.json"           the record, under run_dir/<stage>/, that marks it done
    inputs(cfg, run_dir) -> {name: path}
        the files it reads (upstream records, the kick prior it starts from), each checked
        to exist and parse, with ValueError naming the path, before any long work
    run(cfg, run_dir, say=print) -> record
        the stage: reads its inputs, writes only under run_dir/<stage>/, resumes from its own
        checkpoints there, and returns the record it wrote to OUTPUT

`cfg` is the whole pipeline config (`bumps_jax.config.make_config`); a stage reads its own
section and builds its env from `cfg.env`.
"""

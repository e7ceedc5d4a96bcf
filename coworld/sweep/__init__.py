"""Sweeps: grids of collect -> train -> eval runs (:mod:`~coworld.sweep.grid`), run on local worker processes or a
Ray cluster (:mod:`~coworld.sweep.runner`), each job a sequence of ``coworld`` child processes
(:mod:`~coworld.sweep.jobs`), with a progress view (:mod:`~coworld.sweep.progress`)."""

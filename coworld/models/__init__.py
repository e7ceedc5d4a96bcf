"""DreamerV2's networks, distributions, RSSM, world model and actor-critic (no training loop here).

* :mod:`~coworld.models.networks`: conv encoder/decoder, MLP, layer-normed GRU cell;
* :mod:`~coworld.models.distributions`: straight-through categorical, truncated/tanh normal, unit Gaussian;
* :mod:`~coworld.models.rssm`: the recurrent state-space model with discrete latents;
* :mod:`~coworld.models.world_model`: encoder + RSSM + decoder + reward/discount heads and their loss;
* :mod:`~coworld.models.actor_critic`: imagination, lambda-returns, actor and critic losses, slow critic;
* :mod:`~coworld.models.autotune`: the fastest of equivalent forms of an operation on this machine.

Import from the submodules (this package re-exports nothing, so :mod:`coworld.losses.dreamer` can import
:mod:`~coworld.models.distributions` without a cycle).
"""

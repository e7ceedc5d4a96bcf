"""DreamerV2's networks, distributions, RSSM, world model and actor-critic (no training loop here).

* :mod:`~coworld.models.networks`: conv encoder/decoder, MLP, layer-normed GRU cell;
* :mod:`~coworld.distributions`: straight-through categorical, truncated/tanh normal, unit Gaussian;
* :mod:`~coworld.models.rssm`: the recurrent state-space model with discrete latents;
* :mod:`~coworld.models.world_model`: encoder + RSSM + decoder + reward/discount heads and their loss;
* :mod:`~coworld.models.actor_critic`: imagination, lambda-returns, actor and critic losses, slow critic.

These are the reference: plain PyTorch modules, their architecture chosen by the config. A fast path that computes
the same model in other forms lives in :mod:`coworld.backends` and reads these modules' weights.

Import from the submodules (this package re-exports nothing, so :mod:`coworld.losses.dreamer` can import
:mod:`~coworld.distributions` without a cycle).
"""

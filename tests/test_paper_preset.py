"""The ``paper`` preset, switch by switch: the paper's Table 3 and DreamerV2's design (danijar/dreamerv2's DMC
config), so that a default changed for another preset cannot change it unseen.

Only the listed keys are pinned: a field added later (to ``world_model`` or elsewhere) leaves these tests alone
unless it changes one of them. A pinned key that is renamed or removed fails :func:`test_every_pinned_switch_exists`,
so a rename has to carry its pin along.
"""

from __future__ import annotations

from typing import Any

import pytest

from coworld.config import make_config, to_dict

TABLE_3 = {
    "world_model.kl_scale": 1.0,  # beta1
    "coworld.beta2": 1.5,
    "coworld.k": 0.2,
    "coworld.alpha": 0.2,
    "train.batch_size": 50,
    "train.seq_len": 50,
    "world_model.stoch": 32,  # 32 x 32 discrete latents
    "world_model.classes": 32,
    "world_model.deter": 600,  # RSSM 600 units
    "world_model.lr": 2e-4,
    "actor_critic.actor_lr": 4e-5,
    "actor_critic.critic_lr": 1e-4,
    "actor_critic.horizon": 15,
    "actor_critic.discount": 0.995,
    "actor_critic.lambda_": 0.95,
    # Table 3's update-step rows, read by their names ("target domain update steps": 5e4); see the config's
    # docstring of coworld.target_updates for the swap against Algorithm 1's K1 / K2
    "coworld.target_updates": 50_000,
    "coworld.source_updates": 20_000,
}
"""Table 3 of the paper."""

DREAMERV2 = {
    # the actor: a truncated normal in [-1, 1], trained through the dynamics, DreamerV2's entropy weight
    "actor_critic.actor_dist": "trunc_normal",
    "actor_critic.actor_grad": "dynamics",
    "actor_critic.actor_entropy": 1e-4,
    "actor_critic.actor_min_std": 0.1,
    "actor_critic.actor_advantage": False,
    "actor_critic.actor_absmax": False,
    "actor_critic.return_norm": False,  # no DreamerV3 return normalisation
    # the heads: unit-variance Gaussians (squared errors), not DreamerV3's two-hot; not zero-initialised
    "world_model.reward_dist": "gaussian",
    "actor_critic.critic_dist": "gaussian",
    "world_model.zero_init_reward": False,
    "actor_critic.zero_init_critic": False,
    "world_model.pred_discount": False,  # DMC: no discount head
    # the slow critic: lambda-returns bootstrap from it, copied whole every 100 updates, no regulariser
    "actor_critic.critic_target": "slow",
    "actor_critic.slow_target_every": 100,
    "actor_critic.slow_target_fraction": 1.0,
    "actor_critic.slow_regulariser": 0.0,
    # the latents and the KL: no uniform mixture, balance 0.8, 1 free nat averaged over the batch
    "world_model.unimix": 0.0,
    "world_model.kl_balance": 0.8,
    "world_model.free_nats": 1.0,
    # the conv stacks: 4 x 4 kernels down, 5, 5, 6, 6 up, ELU without normalisation; the loss terms unscaled
    "world_model.encoder_kernels": (4, 4, 4, 4),
    "world_model.decoder_kernels": (5, 5, 6, 6),
    "world_model.act": "elu",
    "world_model.norm": "none",
    "world_model.image_scale": 1.0,
    "world_model.reward_scale": 1.0,
    "world_model.discount_scale": 1.0,
    # the GRU cell: DreamerV2's, with a bias and LayerNorm's epsilon at 1e-3
    "world_model.gru_bias": True,
    "world_model.gru_eps": 1e-3,
    # the networks: ELU MLPs without LayerNorm, CNN depth 48, 400-unit 4-layer heads, actor and critic
    "world_model.mlp_norm": "none",
    "world_model.mlp_act": "elu",
    "actor_critic.mlp_norm": "none",
    "actor_critic.mlp_act": "elu",
    "world_model.cnn_depth": 48,
    "world_model.hidden": 600,
    "world_model.mlp_units": 400,
    "world_model.mlp_layers": 4,
    "actor_critic.units": 400,
    "actor_critic.layers": 4,
    # the optimisers: Adam eps 1e-5, DreamerV2's weight decay 1e-6, gradient clip 100
    "world_model.eps": 1e-5,
    "world_model.weight_decay": 1e-6,
    "world_model.grad_clip": 100.0,
    "actor_critic.eps": 1e-5,
    "actor_critic.weight_decay": 1e-6,
    "actor_critic.grad_clip": 100.0,
    # the online schedule: an update every 5 environment steps, 1000 prefill steps, 100 pretraining updates
    "train.train_every": 5,
    "train.prefill": 1000,
    "train.pretrain_updates": 100,
    "train.actor_warmup": 0,
    "train.expl_noise": 0.0,
}
"""DreamerV2's design (its DMC config; /work/shared/REFERENCE.md section 1), where the paper builds on it."""

COWORLD = {
    # the three terms on, each as the paper reads it: Eq. 3 on the posteriors, Eq. 6 without a rescale
    "coworld.align": True,
    "coworld.align_on": "latent",
    "coworld.reward_relabel": True,
    "coworld.value_reg": True,
    "coworld.zeta": 1.0,
}
"""CoWorld's switches: every term on, in the paper's reading."""

PINNED = {**TABLE_3, **DREAMERV2, **COWORLD}


def _value(tree: dict[str, Any], dotted: str) -> Any:
    node: Any = tree
    for part in dotted.split("."):
        node = node[part]
    return node


def test_every_pinned_switch_exists() -> None:
    """Each pinned key is a leaf of the paper preset's config (a renamed key must take its pin with it)."""
    paper = to_dict(make_config("paper"))
    missing = []
    for dotted in PINNED:
        try:
            value = _value(paper, dotted)
        except KeyError:
            missing.append(dotted)
            continue
        assert not isinstance(value, dict), dotted
    assert not missing, missing


@pytest.mark.parametrize("dotted", sorted(PINNED))
def test_the_paper_preset_keeps_table_3_and_dreamerv2s_design(dotted: str) -> None:
    """The paper preset's value for one pinned switch, compared with its type (``1`` is not ``True``)."""
    value = _value(to_dict(make_config("paper")), dotted)
    want = PINNED[dotted]
    assert type(value) is type(want) and value == want, (
        f"paper preset {dotted}={value!r}, Table 3 / DreamerV2: {want!r}"
    )


def test_overriding_another_presets_switch_leaves_the_paper_preset_alone() -> None:
    """Presets are layers over one set of defaults: building the cpu preset (which turns DreamerV3's switches on)
    and overriding a pinned key there changes nothing in a paper config built after."""
    make_config("cpu", ["actor_critic.actor_dist=normal", "world_model.unimix=0.05"])
    paper = to_dict(make_config("paper"))
    assert {dotted: _value(paper, dotted) for dotted in PINNED} == PINNED

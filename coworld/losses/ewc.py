"""Elastic weight consolidation (Kirkpatrick et al., 2017, Eq. 3) as pure functions.

After learning task A, a network keeps close to its weights ``theta*_A`` where they mattered to A while it learns
task B::

    L(theta) = L_B(theta) + sum_i lambda / 2 * F_i * (theta_i - theta*_A,i)^2

``F`` is the diagonal of the Fisher information of A's loss at ``theta*_A``, estimated from squared gradients.

* :func:`fisher_diagonal`: ``F`` from the gradients of ``N`` batches of A's data;
* :func:`ewc_penalty`: the sum, one scalar per named parameter set.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

__all__ = ["ewc_penalty", "fisher_diagonal"]


def fisher_diagonal(grads: Sequence[Mapping[str, Tensor]], samples: int = 1) -> dict[str, Tensor]:
    """``F_i = samples / N * sum_n g_n,i^2``: the mean squared gradient of ``N`` batches, per parameter.

    Each ``g_n`` is the gradient of a batch's *mean* loss over ``samples`` steps. Where the steps' own gradients
    are independent with mean zero (at the optimum of A), the batch mean's square is ``1 / samples`` of one step's,
    so multiplying by ``samples`` estimates the Fisher of one step's loss (Kirkpatrick et al.'s per-sample ``F``).

    Args:
        grads: ``N >= 1`` dicts ``name -> gradient``, every dict with the same names and shapes.
        samples: steps whose losses each batch's loss averages (1: the batches' own squared gradient).

    Returns:
        ``name -> F`` of the parameter's shape.
    """
    if not grads:
        raise ValueError("fisher_diagonal needs the gradients of at least one batch")
    names = set(grads[0])
    for grad in grads[1:]:
        if set(grad) != names:
            raise ValueError(f"every batch must give the same parameters; {sorted(names ^ set(grad))} differ")
    return {name: samples * torch.stack([g[name].float().square() for g in grads]).mean(dim=0) for name in grads[0]}


def ewc_penalty(
    params: Mapping[str, Tensor], anchor: Mapping[str, Tensor], fisher: Mapping[str, Tensor], weight: float
) -> Tensor:
    """``weight / 2 * sum_i F_i (theta_i - theta*_i)^2`` over the parameters named in ``anchor``.

    Args:
        params: ``name -> theta`` (with gradient), a superset of ``anchor``'s names.
        anchor: ``name -> theta*`` (the source weights).
        fisher: ``name -> F`` of the same names and shapes.
        weight: lambda.

    Returns:
        A scalar.
    """
    if set(anchor) != set(fisher):
        raise ValueError(f"anchor and fisher must name the same parameters; {sorted(set(anchor) ^ set(fisher))} differ")
    missing = set(anchor) - set(params)
    if missing:
        raise ValueError(f"parameters {sorted(missing)} are anchored but not given")
    terms = [(fisher[name] * (params[name].float() - anchor[name].float()).square()).sum() for name in sorted(anchor)]
    if not terms:
        return torch.zeros(())
    return 0.5 * weight * torch.stack(terms).sum()

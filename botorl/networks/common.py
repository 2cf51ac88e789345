"""MLP, Q ensembles, V network, SAC temperature."""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


def default_init(scale: float = 1.0):
    # Xavier-uniform as in jaxrl/rlpd; keeps LayerNorm-free nets well scaled too.
    return nn.initializers.variance_scaling(scale, "fan_avg", "uniform")


class MLP(nn.Module):
    """Dense -> (dropout) -> (LayerNorm) -> relu per hidden layer (the RLPD order)."""

    hidden_dims: Sequence[int]
    activate_final: bool = False
    use_layer_norm: bool = False
    dropout_rate: float | None = None

    @nn.compact
    def __call__(self, x: jax.Array, training: bool = False) -> jax.Array:
        for i, size in enumerate(self.hidden_dims):
            x = nn.Dense(size, kernel_init=default_init())(x)
            if i + 1 < len(self.hidden_dims) or self.activate_final:
                if self.dropout_rate is not None and self.dropout_rate > 0:
                    x = nn.Dropout(rate=self.dropout_rate)(x, deterministic=not training)
                if self.use_layer_norm:
                    x = nn.LayerNorm()(x)
                x = nn.relu(x)
        return x


class QNetwork(nn.Module):
    """One Q(s, a) -> (B,)."""

    hidden_dims: Sequence[int]
    use_layer_norm: bool = False

    @nn.compact
    def __call__(self, observations: jax.Array, actions: jax.Array) -> jax.Array:
        x = jnp.concatenate([observations, actions], axis=-1)
        x = MLP(self.hidden_dims, activate_final=True, use_layer_norm=self.use_layer_norm)(x)
        return nn.Dense(1, kernel_init=default_init())(x)[..., 0]


class CriticEnsemble(nn.Module):
    """N independent Q networks evaluated on the same inputs: output (N, B).

    ``nn.vmap`` stacks the parameters of the members (leading axis N on every leaf) and runs
    them as one batched computation, which is what makes 10 critics affordable.
    """

    hidden_dims: Sequence[int]
    num: int = 2
    use_layer_norm: bool = False

    @nn.compact
    def __call__(self, observations: jax.Array, actions: jax.Array) -> jax.Array:
        ensemble = nn.vmap(
            QNetwork,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            out_axes=0,
            axis_size=self.num,
        )
        return ensemble(self.hidden_dims, self.use_layer_norm, name="members")(observations, actions)


class ValueNetwork(nn.Module):
    """V(s) -> (B,)."""

    hidden_dims: Sequence[int]
    use_layer_norm: bool = False

    @nn.compact
    def __call__(self, observations: jax.Array) -> jax.Array:
        x = MLP(self.hidden_dims, activate_final=True, use_layer_norm=self.use_layer_norm)(observations)
        return nn.Dense(1, kernel_init=default_init())(x)[..., 0]


class Temperature(nn.Module):
    """SAC entropy temperature, parameterised as log_temp so it stays positive."""

    init_value: float = 1.0

    @nn.compact
    def __call__(self) -> jax.Array:
        log_temp = self.param("log_temp", lambda _: jnp.full((), jnp.log(self.init_value), jnp.float32))
        return jnp.exp(log_temp)


def subsample_ensemble(key: jax.Array, params, num_sample: int, num_total: int, replace: bool):
    """Pick ``num_sample`` of ``num_total`` members of an ensemble's parameters.

    With ``replace=True`` indices are drawn independently (WSRL); without, a random subset of
    distinct members (RLPD). Returns the parameter pytree with leading axis ``num_sample``.
    """
    if num_sample == num_total and not replace:
        return params
    if replace:
        idx = jax.random.randint(key, (num_sample,), 0, num_total)
    else:
        idx = jax.random.permutation(key, num_total)[:num_sample]
    return jax.tree_util.tree_map(lambda p: p[idx], params)

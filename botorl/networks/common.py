"""MLP, Q ensembles, V network, SAC temperature."""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


# ------------------------------------------------------------------------------ LayerNorm
# XLA on the CPU runs LayerNorm's row reductions far slower than PyTorch's fused kernel; as
# matmuls with a 1/n column and a hand-written backward they run ~3x faster
# (docs/performance.md). Two-pass variance (centre, then mean of squares) is also more
# accurate than flax's E[x^2] - E[x]^2 when the mean is large. HIGHEST precision keeps GPUs
# from doing these dots in TF32.


def _row_mean(z: jax.Array) -> jax.Array:
    n = z.shape[-1]
    return jnp.dot(z, jnp.full((n, 1), 1.0 / n, z.dtype), precision=jax.lax.Precision.HIGHEST)


def _standardize_fwd(x: jax.Array, eps: jax.Array):
    xc = x - _row_mean(x)
    r = jax.lax.rsqrt(_row_mean(xc * xc) + eps)
    y = xc * r
    return y, (y, r)


@jax.custom_vjp
def _standardize_vjp(x: jax.Array, eps: jax.Array) -> jax.Array:
    return _standardize_fwd(x, eps)[0]


def _standardize_bwd(res, dy):
    y, r = res
    # d/dx of (x - mean) / sqrt(var + eps), with y the output and r = 1 / sqrt(var + eps)
    return r * (dy - _row_mean(dy) - y * _row_mean(dy * y)), None


_standardize_vjp.defvjp(_standardize_fwd, _standardize_bwd)


def standardize(x: jax.Array, eps: float = 1e-6) -> jax.Array:
    """(x - mean) / sqrt(var + eps) over the last axis."""
    return _standardize_vjp(x, jnp.asarray(eps, x.dtype))


class LayerNorm(nn.Module):
    """flax.linen.LayerNorm's function and parameters (``scale``, ``bias``; auto-named
    ``LayerNorm_<i>`` as flax's is), with the fast standardisation above."""

    epsilon: float = 1e-6

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        n = x.shape[-1]
        scale = self.param("scale", nn.initializers.ones, (n,), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros, (n,), jnp.float32)
        return standardize(x, self.epsilon) * scale + bias


class MLP(nn.Module):
    """Dense -> (dropout) -> (LayerNorm) -> relu per layer (the RLPD order), the last included."""

    hidden_dims: Sequence[int]
    use_layer_norm: bool = False
    dropout_rate: float | None = None

    @nn.compact
    def __call__(self, x: jax.Array, training: bool = False) -> jax.Array:
        for size in self.hidden_dims:
            x = nn.Dense(size, kernel_init=nn.initializers.xavier_uniform())(x)  # as jaxrl/rlpd
            if self.dropout_rate is not None and self.dropout_rate > 0:
                x = nn.Dropout(rate=self.dropout_rate)(x, deterministic=not training)
            if self.use_layer_norm:
                x = LayerNorm()(x)
            x = nn.relu(x)
        return x


class QNetwork(nn.Module):
    """One Q(s, a) -> (B,); given the observations alone, V(s) (``ValueNetwork``, IQL's)."""

    hidden_dims: Sequence[int]
    use_layer_norm: bool = False

    @nn.compact
    def __call__(self, *inputs: jax.Array) -> jax.Array:
        x = inputs[0] if len(inputs) == 1 else jnp.concatenate(inputs, axis=-1)
        x = MLP(self.hidden_dims, use_layer_norm=self.use_layer_norm)(x)
        return nn.Dense(1, kernel_init=nn.initializers.xavier_uniform())(x)[..., 0]


ValueNetwork = QNetwork


class CriticEnsemble(nn.Module):
    """N independent Q networks evaluated on the same inputs: output (N, B). ``nn.vmap`` stacks
    their parameters (leading axis N) and runs them as one batched computation."""

    hidden_dims: Sequence[int]
    num: int = 2
    use_layer_norm: bool = False

    @nn.compact
    def __call__(self, observations: jax.Array, actions: jax.Array) -> jax.Array:
        ensemble = nn.vmap(QNetwork, variable_axes={"params": 0}, split_rngs={"params": True}, in_axes=None, out_axes=0,
                           axis_size=self.num)
        return ensemble(self.hidden_dims, self.use_layer_norm, name="members")(observations, actions)


class Temperature(nn.Module):
    """SAC entropy temperature, parameterised as log_temp so it stays positive."""

    init_value: float = 1.0

    @nn.compact
    def __call__(self) -> jax.Array:
        log_temp = self.param("log_temp", lambda _: jnp.full((), jnp.log(self.init_value), jnp.float32))
        return jnp.exp(log_temp)


# CQL's Lagrange multiplier alpha' (agents/cql.py) is a positive scalar learnt through its log,
# exactly the temperature's parametrisation (Cal-QL's JaxCQL builds both from one Scalar), so it
# is this module under its own name; its parameter keeps the name ``log_temp``, which
# checkpoints hold.
LagrangeMultiplier = Temperature


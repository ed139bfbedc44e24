"""Counter-based random streams: every draw a function of its key, so a planner's candidate gets the same numbers
whichever other candidates share its batch (paper, §Motion Model: the annealing of each product of experts, and the
kernel draws its start candidates come from; the paper leaves the random stream open).

A ``torch.Generator`` is one sequential stream: when the annealing draws each step's proposals for every problem of a
batch at once, a problem's numbers depend on how many problems came before it. A :class:`KeyedStream` instead hashes
``(seed, problem key, phase, call, element)`` into each number with integer torch operations (a 32-bit
multiply-xorshift mix, products kept below 2**63 so no platform's integer overflow enters), on the keys' device, with
no state but a call counter. Draws of one call are laid out with the problem dim at :attr:`KeyedStream.dim`; the
element index counts the other dims, so padding or reordering the problems changes nothing for any one of them.

The library's draw functions (:func:`pushtorch.se3.random_normal`, :func:`~pushtorch.se3.random_uniform`,
:func:`~pushtorch.se3.multinomial`, the vMF and truncated-Gamma samplers) take either a ``torch.Generator`` (whose
stream is unchanged) or a :class:`KeyedStream`.
"""

from __future__ import annotations

import math

import torch

from pushtorch.errors import InvalidParameterError

Tensor = torch.Tensor

__all__ = ["KeyedStream", "content_keys", "is_keyed", "keyed_seed"]

_MASK = 0xFFFFFFFF
_GOLDEN = 0x9E3779B9


def _mul32(x: Tensor, constant: int) -> Tensor:
    """``x * constant mod 2**32`` for ``x`` in [0, 2**32), in two 16-bit halves (every product < 2**48)."""
    low, high = constant & 0xFFFF, constant >> 16
    return (x * low + (((x * high) & 0xFFFF) << 16)) & _MASK


def _mix(x: Tensor) -> Tensor:
    """A 32-bit avalanche mix (Wellons' lowbias32) of ``x`` in [0, 2**32)."""
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    return x ^ (x >> 16)


def _mix_int(*values: int) -> int:
    """The same mix over Python integers, folding several into one 32-bit key (host side, once per call)."""
    h = 0x6A09E667
    for v in values:
        for part in (v & _MASK, (v >> 32) & _MASK):
            h ^= part
            h = (h ^ (h >> 16)) * 0x7FEB352D & _MASK
            h = (h ^ (h >> 15)) * 0x846CA68B & _MASK
            h ^= h >> 16
    return h


def content_keys(values: Tensor) -> Tensor:
    """``(B,)`` keys hashed from the float32 bits of each row of ``values (B, D)``: a problem keyed by what it is
    (a candidate's start pose and action), so its draws do not depend on where it stands in a list either."""
    if values.dim() != 2 or values.shape[0] == 0:
        raise InvalidParameterError(f"content keys need rows of values (B, D), got shape {tuple(values.shape)}")
    bits = values.detach().float().contiguous().view(torch.int32).long() & _MASK
    h = torch.full(bits.shape[:1], 0x243F6A88, dtype=torch.int64, device=values.device)
    for column in bits.unbind(-1):  # D is a handful of numbers (a pose and an action), not the batch
        h = _mix((h ^ column) & _MASK)
    return h


def keyed_seed(seed: int, key: int) -> int:
    """A ``torch.Generator`` seed for the problem of ``key`` (:func:`content_keys`) under a call's ``seed``: where a
    problem's draws come from a library call that takes a generator (a simulator ensemble) rather than a
    :class:`KeyedStream`."""
    return (int(seed) * 0x9E3779B97F4A7C15 + int(key)) & 0x7FFFFFFFFFFFFFFF

def is_keyed(generator) -> bool:
    """Whether ``generator`` is a :class:`KeyedStream` (else a ``torch.Generator`` or None)."""
    return isinstance(generator, KeyedStream)


class KeyedStream:
    """A counter-based random stream over ``B`` problems, each with its own integer key.

    Args:
        seed: the stream's seed (an integer in [0, 2**64)).
        keys: ``(B,)`` integer keys, one per problem (a planner's candidate: :func:`content_keys` of its start and
            action); their device is the draws'.
        dim: the dim of every draw's shape that runs over the problems; ``None`` (only with one key): the whole
            draw belongs to that problem.
    """

    def __init__(self, seed: int, keys: Tensor, dim: int | None = 0, _phase: int = 0) -> None:
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**64:
            raise InvalidParameterError(f"a stream's seed must be an integer in [0, 2**64), got {seed!r}")
        keys = torch.as_tensor(keys).reshape(-1)
        if keys.dtype not in (torch.int32, torch.int64) or keys.numel() == 0:
            raise InvalidParameterError("a stream needs at least one integer key")
        if dim is None and keys.numel() != 1:
            raise InvalidParameterError("a stream without a problem dim has exactly one key")
        self.seed, self.keys, self.dim, self.phase = seed, keys.long(), dim, _phase
        self._calls = [0]  # shared with the views of :meth:`along`
        self._mixed_keys = _mix(self.keys & _MASK)

    @property
    def calls(self) -> int:
        """How many calls (draws and forks) this stream has made."""
        return self._calls[0]

    def _next_call(self) -> int:
        call = self._calls[0]
        self._calls[0] += 1
        return call

    @property
    def device(self) -> torch.device:
        return self.keys.device

    def __len__(self) -> int:
        return self.keys.numel()

    def fork(self) -> KeyedStream:
        """A stream of its own for one phase of the work (its draws never meet this stream's); counts as one call
        of this stream, however many draws the phase then makes."""
        phase = _mix_int(self.phase, self._next_call(), 0xF0)
        return KeyedStream(self.seed, self.keys, self.dim, phase)

    def take(self, index) -> KeyedStream:
        """The same stream (phase and call count) for a subset or reordering of the problems; an integer index
        gives one problem's stream whose draws are wholly its own (``dim=None``)."""
        if isinstance(index, int):
            out = KeyedStream(self.seed, self.keys[index : index + 1], None, self.phase)
        else:
            out = KeyedStream(self.seed, self.keys[torch.as_tensor(index, device=self.device)], self.dim, self.phase)
        out._calls = [self.calls]
        return out

    def along(self, dim: int | None) -> KeyedStream:
        """This stream, its call count shared, with the problems along another dim of the draws."""
        out = KeyedStream.__new__(KeyedStream)
        out.__dict__.update(self.__dict__)  # the same _calls list
        out.dim = dim
        return out

    def _bits(self, shape, per_element: int = 1) -> Tensor:
        """32-bit hashes ``(*shape, per_element)`` (int64) of one call."""
        shape = torch.Size(shape)
        base = _mix_int(self.seed, self.phase, self._next_call())
        if self.dim is None:
            inner, keys = shape, self._mixed_keys.reshape(())
            layout = [1] * len(shape)
        else:
            dim = self.dim % len(shape) if len(shape) else 0
            if len(shape) == 0 or shape[dim] != len(self):
                raise InvalidParameterError(f"a keyed draw of shape {tuple(shape)} needs its dim {self.dim} to run "
                                            f"over the stream's {len(self)} problems")
            inner = torch.Size([s for i, s in enumerate(shape) if i != dim])
            layout = [1] * len(shape)
            layout[dim] = len(self)
            keys = self._mixed_keys.reshape(layout)
        count = math.prod(inner) * per_element
        if count >= 2**32:
            raise InvalidParameterError(f"a keyed draw of {count} numbers per problem is over 2**32")
        element = _mul32(torch.arange(count, dtype=torch.int64, device=self.device), _GOLDEN)
        element = element.reshape(*inner, per_element)
        if self.dim is not None:
            element = element.unsqueeze(dim)
        keys = keys.reshape(*layout, 1) if layout else keys.reshape(1)
        return _mix(_mix(keys ^ base) ^ element)  # one mix per number; the problem's key mixed once

    def uniform(self, shape, dtype: torch.dtype = torch.float32) -> Tensor:
        """Uniform draws on [0, 1) of ``shape``: 24 bits for float32, 53 for float64."""
        if dtype == torch.float64:
            bits = self._bits(shape, 2)
            value = (bits[..., 0] >> 5).double() * 2.0**26 + (bits[..., 1] >> 6).double()
            return value * 2.0**-53
        return ((self._bits(shape, 1)[..., 0] >> 8).to(torch.float64) * 2.0**-24).to(dtype)

    def normal(self, shape, dtype: torch.dtype = torch.float32) -> Tensor:
        """Standard normal draws of ``shape`` (Box-Muller of two uniforms, computed in float64)."""
        bits = self._bits(shape, 2) >> 5
        u1 = (bits[..., 0].double() + 0.5) * 2.0**-27  # in (0, 1): its log is finite
        u2 = bits[..., 1].double() * 2.0**-27
        return (torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u2)).to(dtype)

    def multinomial(self, weights: Tensor, n: int) -> Tensor:
        """``n`` indices per row of ``weights (R, N)`` (non-negative, each row with a positive sum), with
        replacement, by the inverse of each row's cumulative weights; the problems run along the rows."""
        cumulative = weights.double().cumsum(-1)
        u = self.uniform((weights.shape[0], n), torch.float64).to(weights.device) * cumulative[:, -1:]
        index = torch.searchsorted(cumulative, u, right=True)
        return index.clamp_max(weights.shape[-1] - 1)

    def permutation(self, n: int) -> Tensor:
        """A random permutation of ``range(n)`` (one problem's stream)."""
        return torch.argsort(self.uniform((n,), torch.float64))

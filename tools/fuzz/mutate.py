"""Random mutations of valid messages, seeded.

Each mutation takes a valid message of an input topic and changes it one way:

* ``bit_flip``: one random bit of one numeric field (of a float64 value, of an integer
  field, or of a byte of a ``data`` buffer);
* ``field_swap``: two numeric fields exchange their values (``x`` and ``pseudorange``,
  ``width`` and ``row_step``, ``sec`` and ``nanosec``, ...);
* ``scale``: one numeric field multiplied by ``10**k`` (k up to +-300), negated, or set to
  a special value (NaN, inf, 0, the largest float);
* ``truncate``: a ``data`` buffer or a ``fields`` list cut short (or, for messages
  without one, the serialised message);
* ``cdr_bit_flip``, ``cdr_truncate``, ``cdr_garbage``: the serialised (CDR) message with
  flipped bits, cut short, or replaced by random bytes, published as raw bytes: what a
  broken sender or a corrupted transport delivers; such a message may not even decode.

A mutation may leave the message valid (a scaled value that is still plausible): each
mutated message is judged against the message it was made from (:mod:`.plausible`, which
never asks the nodes' validator). One that came out valid is *valid after mutation*: a
node may accept it, and must count it if it refuses it. Every other one is malformed: a
node must refuse it and count it. None may crash or block a node.
"""
from __future__ import annotations

import copy
import math
import struct
from dataclasses import dataclass

import numpy as np
from rclpy.serialization import serialize_message

from .cases import ANY, flip_bit

MUTATION = 'mutation'
OPERATORS = ('bit_flip', 'field_swap', 'scale', 'truncate', 'cdr_bit_flip', 'cdr_truncate',
             'cdr_garbage')
_INT_RANGES = {'int8': (-2**7, 2**7 - 1), 'uint8': (0, 2**8 - 1), 'int16': (-2**15, 2**15 - 1),
               'uint16': (0, 2**16 - 1), 'int32': (-2**31, 2**31 - 1),
               'uint32': (0, 2**32 - 1), 'int64': (-2**63, 2**63 - 1),
               'uint64': (0, 2**64 - 1), 'octet': (0, 255), 'byte': (0, 255)}


@dataclass(frozen=True)
class Leaf:
    """A numeric field of a message: ``parent.name`` (``index`` into a fixed array)."""

    parent: object
    name: str
    kind: str          # 'double', 'float', an integer type, or 'bytes'
    index: int | None = None

    def get(self):
        value = getattr(self.parent, self.name)
        return value if self.index is None else value[self.index]

    def set(self, value) -> None:
        if self.index is None:
            setattr(self.parent, self.name, value)
        else:
            array = getattr(self.parent, self.name)
            array[self.index] = value


def numeric_leaves(msg) -> list[Leaf]:
    """Every numeric field of a message, recursively (bytes buffers as one leaf each)."""
    out = []
    for name, ftype in msg.get_fields_and_field_types().items():
        value = getattr(msg, name)
        base = ftype.split('[')[0].split('<')[0]
        if hasattr(value, 'get_fields_and_field_types'):
            out += numeric_leaves(value)
        elif ftype.startswith('sequence<uint8') or ftype in ('sequence<octet>',) or (
                base in ('uint8', 'octet') and '[' in ftype and name == 'data'):
            out.append(Leaf(msg, name, 'bytes'))
        elif base in ('double', 'float') or base in _INT_RANGES:
            if '[' in ftype:
                out += [Leaf(msg, name, base, i) for i in range(len(value))]
            elif not ftype.startswith('sequence'):
                out.append(Leaf(msg, name, base))
    return out


def _clip_int(kind: str, value: int) -> int:
    low, high = _INT_RANGES[kind]
    return int(min(max(int(value), low), high))


def _as_kind(kind: str, value):
    """``value`` as the field type takes it (floats stay floats; integers clipped into the
    field's range: a wider value cannot be serialised at all)."""
    if kind in ('double', 'float'):
        value = float(value)
        if kind == 'float' and math.isfinite(value) and abs(value) > 3.4e38:
            value = math.copysign(3.4e38, value)
        return value
    if isinstance(value, float) and not math.isfinite(value):
        value = 0
    return _clip_int(kind, int(value))


def _bit_flip(msg, rng) -> str:
    leaves = numeric_leaves(msg)
    leaf = leaves[int(rng.integers(len(leaves)))]
    if leaf.kind == 'bytes':
        data = bytearray(bytes(leaf.get()))
        if not data:
            return f'{leaf.name}: empty'
        i = int(rng.integers(len(data)))
        data[i] ^= 1 << int(rng.integers(8))
        leaf.set(bytes(data))
        return f'{leaf.name}[{i}]'
    value = leaf.get()
    if leaf.kind == 'double':
        leaf.set(flip_bit(value, int(rng.integers(64))))
    elif leaf.kind == 'float':
        (raw,) = struct.unpack('<I', struct.pack('<f', float(value)))
        leaf.set(struct.unpack('<f', struct.pack('<I', raw ^ (1 << int(rng.integers(32)))))[0])
    else:
        bits = 8 * (1 if leaf.kind in ('int8', 'uint8', 'octet', 'byte') else
                    2 if '16' in leaf.kind else 4 if '32' in leaf.kind else 8)
        low, high = _INT_RANGES[leaf.kind]
        flipped = int(value) ^ (1 << int(rng.integers(bits)))
        if flipped > high:                # two's complement of a signed field
            flipped -= 1 << bits
        leaf.set(_clip_int(leaf.kind, flipped if flipped >= low else flipped + (1 << bits)))
    return leaf.name


def _field_swap(msg, rng) -> str:
    leaves = [leaf for leaf in numeric_leaves(msg) if leaf.kind != 'bytes']
    if len(leaves) < 2:
        return 'nothing to swap'
    a, b = rng.choice(len(leaves), 2, replace=False)
    la, lb = leaves[int(a)], leaves[int(b)]
    va, vb = la.get(), lb.get()
    la.set(_as_kind(la.kind, vb))
    lb.set(_as_kind(lb.kind, va))
    return f'{la.name}<->{lb.name}'


def _scale(msg, rng) -> str:
    leaves = [leaf for leaf in numeric_leaves(msg) if leaf.kind != 'bytes']
    leaf = leaves[int(rng.integers(len(leaves)))]
    value = leaf.get()
    choice = int(rng.integers(4))
    if choice == 0:
        new = float(value or 1.0) * 10.0 ** float(rng.integers(-300, 301))
    elif choice == 1:
        new = -float(value)
    elif choice == 2:
        new = [math.nan, math.inf, -math.inf, 0.0, 1.7976931348623157e308][
            int(rng.integers(5))]
    else:
        new = float(value) * float(rng.uniform(-1000, 1000))
    if not math.isfinite(new) or abs(new) > 1e300:
        new = new if leaf.kind in ('double', 'float') else rng.integers(2**31)
    leaf.set(_as_kind(leaf.kind, new))
    return leaf.name


def _truncate(msg, rng) -> str | None:
    if hasattr(msg, 'data') and hasattr(msg, 'height'):
        data = bytes(msg.data)
        msg.data = data[:int(rng.integers(0, max(1, len(data))))]
        return 'data'
    if hasattr(msg, 'fields') and msg.fields:
        msg.fields = list(msg.fields)[:int(rng.integers(len(msg.fields)))]
        return 'fields'
    return None


def mutate(msg, rng: np.random.Generator, operator: str | None = None
           ) -> tuple[object, str, str]:
    """One random mutation of a copy of ``msg``.

    Returns:
        ``(message or raw CDR bytes, operator, detail)``.
    """
    operator = operator or OPERATORS[int(rng.integers(len(OPERATORS)))]
    msg = copy.deepcopy(msg)
    if operator == 'truncate':
        what = _truncate(msg, rng)
        if what is not None:
            return msg, operator, what
        operator = 'cdr_truncate'
    if operator.startswith('cdr_'):
        raw = bytearray(serialize_message(msg))
        if operator == 'cdr_bit_flip':
            for _ in range(int(rng.integers(1, 9))):
                i = int(rng.integers(len(raw)))
                raw[i] ^= 1 << int(rng.integers(8))
            return bytes(raw), operator, f'{len(raw)} bytes'
        if operator == 'cdr_truncate':
            cut = int(rng.integers(0, len(raw)))
            return bytes(raw[:cut]), operator, f'{cut} of {len(raw)} bytes'
        n = int(rng.integers(0, 2 * len(raw) + 1))
        head = bytes(raw[:4]) if rng.random() < 0.5 else b''
        return head + rng.bytes(n), operator, f'{len(head) + n} random bytes'
    detail = {'bit_flip': _bit_flip, 'field_swap': _field_swap, 'scale': _scale}[operator](
        msg, rng)
    return msg, operator, detail


@dataclass(frozen=True)
class MutationKind:
    """A mutation operator on a topic, as reported (``topic:mutation_<operator>``)."""

    topic: str
    operator: str
    expect: str = ANY
    family: str = MUTATION
    heavy: bool = False
    issue: bool = False
    judged: bool = True

    @property
    def kind(self) -> str:
        return f'{self.topic}:mutation_{self.operator}'

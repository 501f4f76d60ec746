"""Child random generators on every numpy the package supports (1.24 and later).

``Generator.spawn`` and ``BitGenerator.seed_seq`` are numpy >= 1.25; Debian 12 ships numpy
1.24.2. :func:`spawn` gives the children ``Generator.spawn`` gives, the same streams, from
the generator's seed sequence.
"""
from __future__ import annotations

import numpy as np


def spawn(rng: np.random.Generator, n: int) -> list[np.random.Generator]:
    """``rng.spawn(n)``: ``n`` independent child generators of ``rng``.

    Each call gives new children (the seed sequence counts the ones it spawned), and the
    parent's own stream is untouched, as with ``Generator.spawn``.

    Args:
        rng: The parent generator (seeded from a ``SeedSequence``, as ``default_rng`` does).
        n: How many children.

    Returns:
        The children, each with a bit generator of the parent's type.

    Raises:
        TypeError: The parent's seed sequence cannot spawn (e.g. a legacy ``RandomState``
            seeding).
    """
    if hasattr(rng, 'spawn'):                    # numpy >= 1.25
        return rng.spawn(n)
    return spawn_from_seed_sequence(rng, n)


def spawn_from_seed_sequence(rng: np.random.Generator, n: int
                             ) -> list[np.random.Generator]:
    """What ``Generator.spawn`` does (numpy 1.25's implementation), for numpy < 1.25.

    Args:
        rng: The parent generator.
        n: How many children.

    Returns:
        The children.

    Raises:
        TypeError: The parent's seed sequence cannot spawn.
    """
    bit_generator = rng.bit_generator
    # numpy 1.24 keeps the seed sequence in the (readable) ``_seed_seq`` attribute only.
    seed_seq = getattr(bit_generator, 'seed_seq', None) or bit_generator._seed_seq
    if not isinstance(seed_seq, np.random.SeedSequence):
        raise TypeError(f'the seed sequence {type(seed_seq).__name__} cannot spawn')
    return [np.random.Generator(type(bit_generator)(child)) for child in seed_seq.spawn(n)]

"""The memory one filter epoch needs: the estimate behind the configuration's budget.

:class:`core.config.FilterConfig` refuses sizes whose epoch would exceed
``EPOCH_MEMORY_BUDGET_BYTES`` even with ``MIN_SATELLITE_LIMIT`` satellites, and uses fewer
satellites where the full count would not fit (``FilterConfig.satellite_limit``).
"""
from __future__ import annotations

import math

from .bias import MAX_TRACKED_SATELLITES
from .fusion import MAX_CAMERA_MATCHES
from .gnss_checks import MAX_EPOCH_SATELLITES

#: Largest estimated peak memory of one epoch (:func:`epoch_memory_bytes`) a
#: configuration may need [bytes]: a quarter of an 8 GB vehicle computer, which leaves
#: the rest of the graph (camera_node's database, the DDS buffers) room. Every size this
#: repository documents and benchmarks fits (``gnsscam_bench``: 100,000 particles x 10
#: motion samples, with up to 50 satellites; bias_model 'none' with the default 200
#: posteriors: 23), the sizes that die do not (n_particles = 10,000,000: 158 GiB at 16
#: satellites; bias_model 'none' with n_posteriors = 10,000: 84 GiB).
EPOCH_MEMORY_BUDGET_BYTES = 2 * 2 ** 30
#: Fewest satellites per epoch a configuration must afford within the budget: one
#: constellation in view (up to ~12) and some of a second; fewer would discard usable
#: geometry in every epoch.
MIN_SATELLITE_LIMIT = 16

# Bytes per array element an epoch holds at its peak (docs/nodes.md "Memory per epoch"), measured
# with tracemalloc on the filter (numpy registers its buffers there) and rounded up to
# what the code allocates at worst. S motion samples, N particles (the heading acquisition
# set while it lasts), k satellites, K camera images, M posteriors of N_int particles:
#: Per sample x particle: the propagated sets of this and the previous epoch (S, N, 4),
#: the process noise, the joint and posterior log-weights.
_BYTES_PER_SAMPLE_PARTICLE = 128
#: Per sample x particle x satellite, held through the whole update: the normalised
#: residuals z (S, N, k).
_BYTES_RESIDUALS = 8
#: ... and the likelihood's temporaries on top of them (particle_raim's E-step, 25 B
#: measured; robust 8 B).
_BYTES_LIKELIHOOD = 32
#: Per image x sample x particle: the camera distributions and their mixture (33 B).
_BYTES_CAMERA = 40
#: Per posterior x particle: distances, weights, the protection level's tail partition
#: and sort (41-64 B measured; 72 when the tail widens to the whole set).
_BYTES_POSTERIOR_PARTICLE = 72
#: Per posterior: the remembered bias of each tracked satellite and of the epoch's.
_BYTES_POSTERIOR = 8 * (MAX_TRACKED_SATELLITES + MAX_EPOCH_SATELLITES)
#: Fixed part (interpreter and small arrays).
_BYTES_FIXED = 16 * 2 ** 20


def epoch_memory_bytes(n_particles: int, acquisition_particles: int, n_posteriors: int,
                       motion_samples: int, satellites: int = MAX_EPOCH_SATELLITES,
                       camera_images: int = MAX_CAMERA_MATCHES) -> int:
    """Estimated peak memory of one filter epoch [bytes], an upper bound of the measured
    peaks (docs/nodes.md "Memory per epoch").

    The residuals live through the update; the likelihood, the camera fusion and the
    integrity bound come one after the other, so the largest of the three counts::

        S N (128 + 8 k) + max(32 S N k, 40 K S N, 72 M N_int) + 8 (256 + 64) M + 16 MiB

    with N the heading acquisition set (the larger of the two sizes) and N_int the evenly
    thinned set the bound sees during acquisition (``SystematicResampler.thin``).

    Args:
        n_particles: N.
        acquisition_particles: Set size during heading acquisition.
        n_posteriors: M.
        motion_samples: S (``FilterConfig.motion_sample_count``).
        satellites: k (default: the most an epoch uses).
        camera_images: K (default: the most an epoch fuses).
    """
    n = max(n_particles, acquisition_particles)
    n_int = math.ceil(n / max(n // n_particles, 1))
    sn = motion_samples * n
    return int(_BYTES_FIXED + sn * (_BYTES_PER_SAMPLE_PARTICLE + _BYTES_RESIDUALS * satellites)
               + max(_BYTES_LIKELIHOOD * sn * satellites, _BYTES_CAMERA * camera_images * sn,
                     _BYTES_POSTERIOR_PARTICLE * n_posteriors * n_int)
               + _BYTES_POSTERIOR * n_posteriors)

"""Memory after a large message: the node processes give it back.

**Where it stayed.** rmw_fastrtps (Jazzy's default RMW, the one of this package's
environment) creates every DataReader with the history memory policy
``PREALLOCATED_WITH_REALLOC``: each slot of a reader's history keeps its payload buffer,
grown to the largest sample it ever held and never shrunk. The nodes refuse an 8000x8000
image (192 MB serialised) by its header fields, but Fast DDS has reassembled it in such a
buffer before (also an image that lost a fragment on camera_node's best-effort
subscription and is never delivered): the 192 MB stay resident for the life of the
process. Measured on pipeline_node (two such images, then 20 valid 640x480 ones): RSS
283 -> 493 MB with camera_node's best-effort subscription, 274 -> 464 MB with a reliable
one (both images refused as too large); the buffer is a live allocation of Fast DDS
(``malloc_info``: 195 MB in use in mmapped chunks), ``malloc_trim(0)`` gave back nothing.

**The remedy.** :func:`configure_node_memory`, called by every node process before
``rclpy.init``, points Fast DDS at :data:`PROFILE` with ``RMW_FASTRTPS_USE_QOS_FROM_XML=1``:
the readers' history memory becomes ``DYNAMIC`` (each sample's payload allocated for it
and freed once taken or dropped), everything else stays as rmw_fastrtps sets it without
a file. Same measurements: 272 -> 280 MB and 272 -> 284 MB (the memory goes back once the
incomplete image is dropped or the refused one taken).

**Not the cause: glibc malloc.** A block above the largest dynamic mmap threshold (32 MB
on 64-bit) is always mmapped and unmapped on free, so a big message that Python or rmw
frees goes back at once; ``malloc_trim(0)`` after the garbage (with the profile) gave back
3-6 MB, and 10,000-satellite clouds (480 kB each, below that threshold) left 2 MB. No
``mallopt`` or trimming is needed for that.

**Speed: the filter's epoch arrays.** An epoch allocates a few arrays of megabytes (the
propagated sets: 3.2 MB at N = 10,000 x M = 10) and frees them when it ends; glibc hands
freed memory at the top of the heap back to the kernel (trim threshold), so the next epoch
faults fresh zeroed pages in again: ~700 page faults per epoch at N = 10,000, 3,400 at
100,000. :func:`keep_epoch_memory` (the start-up of fusion_node, and of pipeline_node, whose
process runs fusion_node's epochs) keeps blocks up to 32 MB (glibc's largest mmap
threshold) on the heap and the freed heap up to 256 MB with the process: one page fault
per epoch afterwards. Larger blocks (an 8000x8000 image) are
still mapped and unmapped on their own, so a big message still goes back at once; the
resident memory of fusion_node stays at the high-water mark of its epochs (tens of MB at
N = 10,000). (``gnsscam_bench`` keeps glibc's defaults: its yardstick, plain numpy, gains
even more from the setting than the epoch.)

**Pauses: the garbage collector.** A node process holds about 150,000 objects the
cyclic garbage collector tracks once it has started (rclpy, numba's dispatchers, the
package, the kernels' warm-up), nearly all of them alive until it exits. Each full
collection walks all of them: 54-70 ms (a started pipeline_node's modules; ``python -m
gnsscam_ros.bench.pauses``: 70 ms), the time of 60 epochs at N = 120 and far beyond the
10 ms an epoch may take. The collector starts one when the objects that survived since
the last exceed a quarter of the long-lived ones: soon after a start-up that left many
pending (seen once in 2,000 epochs of ``gnsscam_bench``'s engine loop right after its
warm-up: a 68 ms epoch), and whenever a running process has kept enough new objects.
:func:`freeze_start_up_objects` (:func:`gnsscam_ros.nodes.runtime.start_nodes`, once every
node of the process is built) collects once and moves what survives into the collector's
permanent generation: later collections walk only what the running nodes allocate (the
same benchmark: a full collection 0.4 ms after the freeze). Reference counting still
frees a frozen object the moment it is no longer used; only a reference cycle among
start-up objects that become garbage later would stay.

**Discovery.** The same profile makes each participant announce itself every 0.5 s
instead of Fast DDS's 3 s: a node that restarts meets the running ones at their next
announcement, so within a second rather than up to 3 s (measured: a new participant saw a
running node after 0.26-0.64 s, against 0.27-3.2 s before).

Fast DDS reads the profile file when the process creates its first participant, so the
settings must be in the environment before that; child processes inherit them.
"""
from __future__ import annotations

import ctypes
import gc
import os
from pathlib import Path
from typing import MutableMapping

#: The node processes' Fast DDS profile (package data next to this module).
PROFILE = Path(__file__).with_name('fastdds_profile.xml')
#: Fast DDS 2.x reads its XML profiles from this file (Jazzy); Fast DDS 3 renamed it.
PROFILE_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'
PROFILE_ENV_V3 = 'FASTDDS_DEFAULT_PROFILES_FILE'
#: Fast DDS also loads this file from the working directory.
CWD_PROFILE = 'DEFAULT_FASTRTPS_PROFILES.xml'
#: 1: rmw_fastrtps takes history memory, publication mode and data sharing from the XML.
QOS_FROM_XML_ENV = 'RMW_FASTRTPS_USE_QOS_FROM_XML'
#: Ignored by rmw_fastrtps with QOS_FROM_XML_ENV=1: set, the user's choice wins.
PUBLICATION_MODE_ENV = 'RMW_FASTRTPS_PUBLICATION_MODE'


def use_fastdds_profile(path: str | Path,
                        environ: MutableMapping[str, str] | None = None) -> str | None:
    """Make ``path`` the Fast DDS profile of this process and its children, with its
    history memory and publication settings in force, unless the user configures Fast
    DDS.

    The user's configuration wins: a profile file of their own (``PROFILE_ENV``, its Fast
    DDS 3 name, or ``DEFAULT_FASTRTPS_PROFILES.xml`` in the working directory) leaves the
    environment alone; ``RMW_FASTRTPS_USE_QOS_FROM_XML`` or
    ``RMW_FASTRTPS_PUBLICATION_MODE`` set keeps it as it is (``path`` then gives only what
    rmw_fastrtps does not override, e.g. transports). Another RMW: nothing to do.

    Args:
        path: The XML profile file.
        environ: The environment to change (default: this process's).

    Returns:
        The profile file in force (the user's or ``path``), None when there is none (not
        Fast DDS).
    """
    env = os.environ if environ is None else environ
    if not env.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp').startswith('rmw_fastrtps'):
        return None
    own = env.get(PROFILE_ENV) or env.get(PROFILE_ENV_V3)
    if own:
        return own
    if Path(CWD_PROFILE).is_file():
        return str(Path(CWD_PROFILE).resolve())
    env[PROFILE_ENV] = str(path)
    if QOS_FROM_XML_ENV not in env and not env.get(PUBLICATION_MODE_ENV):
        env[QOS_FROM_XML_ENV] = '1'
    return str(path)


def configure_node_memory(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Start-up of a node process, before ``rclpy.init``: Fast DDS readers that free a
    message's memory once it is gone (:data:`PROFILE`; see the module docstring).

    Returns:
        The Fast DDS profile file in force (:func:`use_fastdds_profile`); None also for an
        install without :data:`PROFILE` (rmw_fastrtps's own settings then: with
        ``RMW_FASTRTPS_USE_QOS_FROM_XML=1`` and no file, Fast DDS's defaults would replace
        them).
    """
    if not PROFILE.is_file():
        return None
    return use_fastdds_profile(PROFILE, environ)


#: glibc's ``mallopt`` parameters (malloc.h) and the values :func:`keep_epoch_memory` sets.
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
EPOCH_MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024     # glibc's maximum on 64-bit
EPOCH_TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024


def set_malloc_thresholds(mmap_bytes: int, trim_bytes: int) -> bool:
    """Set glibc's mmap and trim thresholds (``mallopt``; setting them also turns off
    glibc's dynamic mmap threshold). True when set; False where the C library is not
    glibc. This process's epochs (:func:`keep_epoch_memory`) and the campaign's Dask
    workers (``evaluation.campaign_cluster.tune_malloc``) set them."""
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, int(mmap_bytes))
                and mallopt(M_TRIM_THRESHOLD, int(trim_bytes)))


def keep_epoch_memory() -> bool:
    """Keep the memory of freed epoch arrays in the process for the next epoch (see the
    module docstring). True when set; False where the C library is not glibc."""
    return set_malloc_thresholds(EPOCH_MMAP_THRESHOLD_BYTES, EPOCH_TRIM_THRESHOLD_BYTES)


def freeze_start_up_objects() -> int:
    """Collect once, then exempt every object alive now from later collections (see the
    module docstring); returns how many were frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


__all__ = ['PROFILE', 'configure_node_memory', 'freeze_start_up_objects', 'keep_epoch_memory',
           'set_malloc_thresholds', 'use_fastdds_profile']

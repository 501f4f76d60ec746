"""The project's fault-injection kit: ``python -m tools.fuzz``.

Three campaigns, each seeded (``--seed``), each printing a table of figures and a one-line
verdict per target (the issue "never crash, never lie"):

* ``messages`` (:mod:`.messages`): pipeline_node in a child process of its own ROS domain; a
  probe node plays a valid short emulated drive (GNSS, IMU, odometry twist, synthetic camera
  frames with a matching map database) in stamp order and, between its epochs, bursts of
  malformed messages on every input topic: structured cases (:mod:`.cases`: the issue's
  list: stamps that do not fit, 1e160 coordinates, flipped exponent bits, 1,000 and 10,000
  satellites, 1.7e308 speeds, 1e300 positions, an 8000x8000 image, far-future stamps, wrong
  layouts, truncated buffers, NaN everywhere, ...) and random mutations of valid messages
  (:mod:`.mutate`: bit flips, field swaps, scaled values, truncations, broken CDR). It
  measures crashes, hangs, blocked epochs, RSS, rejections the nodes count (their
  ``diagnostics``) against what was sent, and the recovery of the estimate against a
  clean pass of the same drive.
* ``processes`` (:mod:`.processes`): the four nodes as separate processes; each is killed
  (SIGKILL) mid-replay and restarted: time until ``integrity_risk`` flows again, and every
  OK verdict checked against the windows where an input it needs was missing or reset.
* ``files`` (:mod:`.files`): corrupt inputs for each command-line tool (bags, libRSF text,
  images, CSVs, map databases, output paths), each tool run on each: tracebacks, exit
  codes against the documented ones, whether the error names the file, files
  overwritten, files left behind.

The figures and verdicts are meant to be reported as they are: a target that fails says
FAIL with the figure next to it.
"""

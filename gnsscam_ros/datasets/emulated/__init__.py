"""The seeded emulated urban drive, its camera stream and its map database.

Modules, each importing only those listed before it (and :mod:`..city`):

* ``config``: parameters and per-ingredient random streams;
* ``route``, ``trajectory``, ``scenario``: the streets driven, the motion along them, and
  the scenario (city, route, motion, frame, start time) that every other step reads;
* ``imu_odometry``, ``constellation``, ``gnss_faults``, ``pseudoranges``: sensor data;
* ``optics``, ``textures``, ``render``: the street imagery;
* ``camera``: the camera stream of a drive (``with_camera``);
* ``drive``: :func:`make_emulated_drive <.drive.make_emulated_drive>`, the whole drive;
* ``views``, ``map_database``, ``retrieval``: the database pass, the cached map database
  built from it, and retrieval accuracy of a camera stream against it.
"""

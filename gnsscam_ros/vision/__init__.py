"""Camera map matching: ORB features, a vocabulary tree and a TF-IDF image database.

``features`` extracts ORB descriptors, ``vocab_tree`` quantises them to visual words with a
hierarchical k-majority tree, ``database`` scores a query image against geotagged database
images (Nister & Stewenius, CVPR 2006), ``synthetic`` draws street images for tests and
benchmarks, and ``mapdb_cli`` is the ``gnsscam_mapdb`` command. This package uses OpenCV;
the particle-side camera distribution is in ``core.fusion`` (``camera_fusion``).
"""

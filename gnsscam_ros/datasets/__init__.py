"""Datasets: the emulated urban drive (``emulated``), the smartLoc (libRSF text) loader,
pseudorange fault injection into any drive (``faults``) and cutting a drive short (``cut``).
"""

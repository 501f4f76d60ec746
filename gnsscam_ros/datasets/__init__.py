"""Datasets: the emulated urban drive and the smartLoc (libRSF text) loader."""

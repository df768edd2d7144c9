"""stereopath host side: receiving, live view, evaluation, dense mapping, reprocessing, CLI.

Heavy libraries (Open3D, evo, rerun, matplotlib) are imported inside the
functions that need them, so ``stereopath --help`` is instant.
"""

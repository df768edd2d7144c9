"""Exports of a scan for the tools people open next: COLMAP, nerfstudio (Gaussian splatting) and MCAP."""

"""Dense mapping: stereo depth, TSDF fusion, the mapper, mesh previews."""

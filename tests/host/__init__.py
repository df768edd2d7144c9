"""Tests of stereopath.host."""

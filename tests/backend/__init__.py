"""Tests of stereopath.backend."""

"""Tests of stereopath.device."""

"""Device-side ``stereopath device ...`` subcommands (no host libraries imported)."""

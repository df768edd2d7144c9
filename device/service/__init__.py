"""The capture service: options, the frame pipeline over its sinks, status, systemd integration, installer."""

"""The wire shared by device and host: message encoders/decoders, CURVE keys, socket options."""

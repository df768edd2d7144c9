"""The live side of the host: receiver, keyframe store, live view, live map."""

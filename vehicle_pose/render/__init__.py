"""Off-screen rendering: the GL context, the renderer, the exterior pass, overlays and synthetic photos."""

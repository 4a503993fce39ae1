"""Searching poses: the optimisers, the view search for start poses and the wheel starts."""

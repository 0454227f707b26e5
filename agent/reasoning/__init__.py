"""Reasoning: object relations, out-of-place detection and placement."""

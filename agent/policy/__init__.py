"""The policy: Algorithm 1 (tidy.py) built from motor skills (skills.py)."""

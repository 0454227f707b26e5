"""tidee."""

"""Optional learned components (the extra ``learning``: PyTorch)."""

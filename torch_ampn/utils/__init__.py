"""Process-level helpers of the package: torch's thread count, ``torch.compile`` and the heap."""

"""CapVector."""

"""Loss functions: pure, returning unreduced named terms."""

"""Evaluation: metrics between shapes, ``recon diff``, ``recon compare``, pictures."""

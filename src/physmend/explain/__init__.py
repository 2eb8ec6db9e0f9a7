"""Explanations: residual analysis, mechanism catalogue and reports."""

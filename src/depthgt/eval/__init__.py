"""Evaluation: depth and pose metrics (one vocabulary), method evaluation, tables, figures."""

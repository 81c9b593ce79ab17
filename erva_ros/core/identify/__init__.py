"""Identification of the model's parameters.

The fit (``fit``), a bag as data (``bag``), the report and params file (``report``).
"""

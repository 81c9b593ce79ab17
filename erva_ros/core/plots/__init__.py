"""Figures written to files: axes and saving (``figures``), closed-loop figures."""

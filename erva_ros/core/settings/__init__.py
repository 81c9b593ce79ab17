"""Every parameter's one home.

What a parameter may be (``specs``), the shipped config files (``files``) and each
node's schema (``schemas``).
"""

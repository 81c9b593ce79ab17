"""Offline studies on the model object.

The closed loop of `erva sim` (``closed_loop``), the frequency response (``fr``), the
sensitivity, the identification study and the map study.
"""

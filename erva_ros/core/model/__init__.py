"""The model object and what is built on it alone.

The ERVA quarter car and the linear benchmark (``quarter_car``), the whole car
(``full_car``, ``car_params``), the physical parameters (``params``), the plant, the
estimators (``estimator``, ``road_estimator``) and the compiled functions (``codegen``).
"""

"""Filters: the estimators themselves, ROS-free and frame-free (lowest layer of fullperc_fusion).

``api`` (the predict/update interface every filter implements, Measurement, Step, Capabilities, Role), ``registry``
(name -> FilterSpec: factory, parameter dataclass, declared capabilities), ``paper_family`` (the paper's KF, BKF,
CKF, CBKF in their general matrix form: the reference), ``paper_kernel`` (the same family's closed-form step per
axis, written once), ``paper_fast`` (that step one sample at a time) and ``paper_batch`` (a whole replay at once),
``fullperc`` / ``fullperc_reference`` (our filter: fast form and its reference; ``fullperc_params`` its parameters,
``so3_float`` its float SO(3) helpers) and its models (``measurement_models``, ``rot_noise_scale``,
``noise_model_file``). Imports nothing else of fullperc_fusion.
"""

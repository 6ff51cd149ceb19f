"""Filters: the estimators themselves, ROS-free and frame-free (lowest layer of fullperc_fusion).

``api`` (the predict/update interface every filter implements), ``registry`` (name -> filter class),
``paper_family`` (the paper's KF, BKF, CKF, CBKF in their general matrix form: the reference), ``paper_fast`` (the
same family in closed form per axis, pinned to the general form), ``paper_batch`` (a whole replay at once),
``fullperc`` / ``fullperc_reference`` (our filter, fast form and its reference), its models (``measurement_models``,
``rot_noise_scale``, ``noise_model_file``) and ``so3`` helpers. Imports nothing else of fullperc_fusion.
"""

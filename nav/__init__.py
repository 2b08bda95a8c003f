"""The stereo navigation assistant (the cloud-navigation-assistant paper's application).

A teleoperated robot's joystick commands are filtered against obstacles seen by an on-board
stereo camera. The stereo processing is one ONNX graph (``zoo:stereo``, built in
:mod:`nav.stereo_graph`), so the runtime can split it like any model; the geometry of the
assistant (distance to collision per curvature, shared control) is numpy in :mod:`nav.curvature`
and :mod:`nav.shared_control`. See docs/navigation.md.
"""

"""Rendered cameras and vision pipelines (dissertation chapter 5).

Modules: :mod:`config` (VisionConfig), :mod:`tags` (AprilTag ids), :mod:`models` (cube and
procedural spacecraft), :mod:`render` (headless pyrender), :mod:`noise` (camera noise),
:mod:`mono` (fiducial pose), :mod:`stereo` (disparity + ICP), :mod:`characterize`
(Monte Carlo error statistics), :mod:`bench`, :mod:`pipeline` (VisionSystem).
Heavy imports (OpenGL, OpenCV, Open3D) happen inside the modules that need them.
"""

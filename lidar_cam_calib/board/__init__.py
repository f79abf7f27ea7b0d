"""The ``board`` method (paper 000, Ou et al., Sensors 2022): a spinning LiDAR and several cameras
calibrated at once from a checkerboard with a reflective border carried around the rig.

* :mod:`.frame` -- :class:`BoardFrame`, :class:`CameraImage`, :class:`BoardGeometry`
* :mod:`.lidar_board` -- the board in a LiDAR sweep (intensity or geometry), ring ends, virtual corners
* :mod:`.image_corners` -- sub-pixel checkerboard corners and their order
* :mod:`.solvers` -- epnp, kabsch_3d3d, paper (free points), ours (joint, LiDAR kept in the problem)
* :mod:`.calibrator` -- :class:`BoardConfig`, :class:`BoardCalibrator` (add / ready / fit / status / reset)
* :mod:`.overlay` -- LiDAR points drawn on each camera image
"""
from .calibrator import BoardCalibrator, BoardConfig
from .frame import BoardFrame, BoardGeometry, CameraImage

__all__ = ["BoardCalibrator", "BoardConfig", "BoardFrame", "BoardGeometry", "CameraImage"]

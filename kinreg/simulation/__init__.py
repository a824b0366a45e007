"""Ground-truth simulator: a planar building, a handheld rotating LiDAR, a walk, SLAM drift, static scans.

Every later stage is tested against this module, so everything is parametrised (scene, sensor,
walk, drift, noise, seed) and deterministic given the configuration.

Frames and conventions (METHOD.md section 4):

- object frame ``obj``: the building's frame, metres; ``z`` up, the floor at ``z = 0``.
- platform frame ``p``: the handheld unit, ``x`` forward, ``y`` left, ``z`` up; the exported
  trajectories are ``T_obj_p``. The sensor origin is the platform origin, so the "sensor-frame"
  points of the simulator are platform-frame points (the head rotation is internal to the
  instrument, as in a GeoSLAM ZEB whose head angle is measured by an encoder).
- A patch's normal points into the free space (towards any scanner that can see it), so the
  two faces of a 0.2 m wall have opposite normals.

The georeferencing is done exactly as SLAM software does it: the 100 Hz trajectory rows are
interpolated (linear position, SLERP rotation, :func:`kinreg.geometry.interpolate_poses`) at every
point time. The rays are cast from the interpolated TRUE trajectory; the exported cloud is mapped
with the interpolated DRIFTED trajectory ``T_slam(t) = D(t) * T_true(t)``.
"""

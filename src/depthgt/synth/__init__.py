"""Synthetic RGB-D scenes: procedural rooms and a Kinect v1 sensor model.

* :mod:`.textures`: tileable procedural albedo textures;
* :mod:`.scene`: room layouts of analytic primitives, exact ray casting, shading;
* :mod:`.camera`: closed-form hand-held camera paths;
* :mod:`.noise`: the Kinect v1 depth model (shadows, holes, quantised disparity);
* :mod:`.calibration`: the shared estimator of hole fractions and depth noise.

The source adapter is :mod:`depthgt.sources.synthetic`.
"""

"""Pure functions: physics, propagation, DSP, geometry, TDOA maths, conformal maths, audio, scene sampling."""

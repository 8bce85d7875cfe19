"""Geometry in metres: rigid transforms (se3), units, pinhole cameras, ray casting, planes, sensor noise,
the BOP pose-error metrics and object symmetries. Depends on nothing else in apose_studio but errors."""

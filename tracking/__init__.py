"""Monocular face tracking: landmark detection, face-model fitting, temporal smoothing."""

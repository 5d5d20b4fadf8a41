"""Body model kernels: SMPL-format LBS model, procedural stand-in model, poses and pose prior."""

"""Dataset generation: VG-dset style 6-DOF grasp datasets from real meshes."""

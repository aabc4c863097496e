"""Point-cloud front end (Open3D): features, descriptor matching and local refinement."""

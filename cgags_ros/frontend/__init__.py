"""
Point-cloud front end: the putative correspondences the core starts from, and refinement.

Downsampling and normals (:mod:`.features`), FPFH descriptors (:mod:`.fpfh`, on the
neighbour search of :mod:`.neighbours`), exact descriptor matching (:mod:`.matching`,
:mod:`.descriptor_index`) and keypoint selection (:mod:`.keypoints`). FPFH and matching are
our own numba code (:mod:`.compiled`); Open3D downsamples, estimates normals, runs ICP
(:mod:`.refine`, or small_gicp) and computes FPFH only for a cloud too spread out for the
neighbour grid.
"""

"""Disparity map -> obstacles: the camera mount and floor plane (mount), the ground per frame
(ground), the default segmenter (layers) and the thesis's (seed), tracks (tracking), free space
(freespace), pictures for people (draw), and the mount from data (mount_estimate)."""

"""ballbot-vision: stereo obstacle detection as Zenoh microservices."""

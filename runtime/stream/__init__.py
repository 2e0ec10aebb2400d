"""Moving frames: the loop (flow limiting, failures, signals), timing statistics, sinks (video, PNGs,
MJPEG over HTTP, session recorder) and the crash-safe session format."""

"""Facts the whole package shares, defined once (core: imports nothing)."""

SAMPLE_RATE = 16_000  # Hz: the audio rate of the phone recogniser, the speech encoders and streams
MOTION_FPS = 30.0  # motion frames per second by default: VOCASET's (captured at 60 fps, read at 30)
INT8_LAYERS = ("speech", "decoders", "all")  # layers a learned model can run in int8 on the CPU

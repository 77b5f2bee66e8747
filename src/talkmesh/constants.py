"""Facts the whole package shares, defined once (core: imports nothing)."""

SAMPLE_RATE = 16_000  # Hz: the audio rate of the phone recogniser, the speech encoders and streams
MOTION_FPS = 30.0  # motion frames per second by default: VOCASET's (captured at 60 fps, read at 30)
INT8_LAYERS = ("speech", "decoders", "all")  # layers a learned model can run in int8 on the CPU
CHUNK_FRAMES = 256  # frames per chunk of generate_chunks (15 MB of float32 vertices at V=4766)


def frames_for_audio(samples: int, fps: float) -> int:
    """Motion frames of ``samples`` audio samples at ``fps`` (at least one)."""
    return max(1, round(samples / SAMPLE_RATE * fps))


# The released datasets' training speakers, in the order of the official one-hot style columns
# (FaceFormer and CodeTalker): the dataset readers' splits and the checkpoint importer share them.
VOCASET_TRAIN_SUBJECTS = (
    "FaceTalk_170728_03272_TA",
    "FaceTalk_170904_00128_TA",
    "FaceTalk_170725_00137_TA",
    "FaceTalk_170915_00223_TA",
    "FaceTalk_170811_03274_TA",
    "FaceTalk_170913_03279_TA",
    "FaceTalk_170904_03276_TA",
    "FaceTalk_170912_03278_TA",
)
BIWI_TRAIN_SUBJECTS = ("F2", "F3", "F4", "M3", "M4", "M5")

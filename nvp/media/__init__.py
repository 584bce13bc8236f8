"""Media I/O with PyAV (no system ffmpeg): probing, frame iteration, audio reading and MP4 writing.

One module per job: :mod:`nvp.media.probe` (what a file holds), :mod:`nvp.media.frames` (decoding frames),
:mod:`nvp.media.audio` (reading audio, whole or block by block; what an mp4's AAC track stores),
:mod:`nvp.media.writer` (writing mp4 files). Import from ``nvp.media``.

Conventions used throughout:

* Video frames are RGB ``uint8`` arrays of shape ``(H, W, 3)``, already rotated for display.
* Audio is ``float32`` mono in ``[-1, 1]``, shape ``(num_samples,)``.
* Times are in seconds, measured from the first frame (video) or first sample (audio) of the stream.
* Frame rates may be fractional (29.97 = 30000/1001); they are handled as exact fractions internally.
"""

from nvp.media.audio import (
    AAC_MAX_CHANNELS,
    AAC_RATES,
    AUDIO_LAYOUTS,
    AudioBlocks,
    aac_rate,
    read_audio,
    storable_audio,
)
from nvp.media.frames import FORWARD_GAP_S, frames_at, iter_frames
from nvp.media.probe import VideoInfo, audio_rate, has_audio, probe_video, rotate_frame
from nvp.media.writer import VideoWriter

__all__ = [
    "AAC_MAX_CHANNELS",
    "AAC_RATES",
    "AUDIO_LAYOUTS",
    "AudioBlocks",
    "FORWARD_GAP_S",
    "VideoInfo",
    "VideoWriter",
    "aac_rate",
    "audio_rate",
    "frames_at",
    "has_audio",
    "iter_frames",
    "probe_video",
    "read_audio",
    "rotate_frame",
    "storable_audio",
]

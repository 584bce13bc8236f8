"""Expressions of long audio in blocks (``nvp dub``): memory that does not grow with the audio's length.

:func:`nvp.person.predict_expressions` reads the whole audio at once: it holds its 16 kHz samples (3.8 MB a
minute) and one kind of per-frame features at a time (2-5 MB a minute), so a 30-minute dub peaked higher
than a 1-minute one. :class:`BlockedExpressions` takes the audio as it is decoded, piece by piece
(:class:`nvp.media.AudioBlocks`), and predicts the frames of :data:`BLOCK_S` seconds at a time from that
block's audio with :data:`CONTEXT_S` seconds more on each side, with :func:`predict_expressions` itself. The
first half of the context after a block is faded linearly into the next block's prediction of it (as the
features' chunks are cross-faded), so the mouth does not jump at a block's edge; the rest of the context's
frames are dropped. Only a block and its context are ever held.

Audio shorter than ``BLOCK_S + CONTEXT_S`` is one block: exactly :func:`predict_expressions` of all of it.
Longer audio differs from that only near the blocks' edges, as whole-file prediction itself differs with
the audio's length (the features are made in 28 s chunks cross-faded over 4 s, planned over the length
read, :mod:`nvp.audio_features`; the voice-activity detector's state starts where its audio starts); what
the context costs and changes is measured by ``scripts/bench/long_audio.py``. With a transcript the text is
aligned to all the audio, so all of it is one block.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from nvp.allocator import release_freed_memory
from nvp.audio_features import SAMPLE_RATE
from nvp.errors import NvpError

if TYPE_CHECKING:
    from nvp.audio2exp import Audio2ExpressionNet
    from nvp.person_style import PersonStyle

BLOCK_S = 120.0
"""Seconds of frames predicted at a time: the features of a block and its context (128 s) take about 30 MB
more than a 1-minute dub's, whose peak is its rendering's, not its features'."""
CONTEXT_S = 4.0
"""Seconds of audio before and after a block that its prediction also reads, the features' own cross-fade
(see the module docstring). ``scripts/bench/long_audio.py``, 10 minutes of eight speech clips in four
languages, a test person at 30 fps (AMD EPYC): the largest frame-to-frame step of the inner-lip gap at a
block's edge 0.52 cm with no context (the whole file's 99th percentile of steps: 0.46 cm), 0.21 cm with 4 s
(the whole file's there: 0.17 cm); 10 s changed nothing more."""


class BlockedExpressions:
    """Feed mono 16 kHz audio with :meth:`push` in pieces of any length, then :meth:`finish`
    returns the expressions ``(T, K_exp)`` of all of it at ``fps`` (as :func:`predict_expressions` would of
    the whole audio; see the module docstring). :meth:`has_speech` then says whether it held speech
    (:func:`nvp.vad.speech_activity` of the whole audio, its 32 ms chunks counted block by block).
    ``transcript``: ``(text, language)`` of what the audio says (all of the audio is then one block)."""

    def __init__(
        self,
        style: PersonStyle,
        net: Audio2ExpressionNet,
        fps: float,
        transcript: tuple[str, str] | None = None,
        block_s: float = BLOCK_S,
        context_s: float = CONTEXT_S,
    ) -> None:
        if not (block_s > 0 and context_s >= 0):
            raise ValueError(f"expected a block > 0 s and a context >= 0 s, not {block_s}, {context_s}")
        self.style, self.net, self.fps = style, net, float(fps)
        self.transcript = transcript
        self.block = max(1, int(round(block_s * self.fps)))  # frames
        self.context = int(round(context_s * self.fps))
        self.received = 0  # samples pushed so far
        self.held = 0  # of them, samples held now (a block and its context at most, and the last piece)
        self._pieces: list[np.ndarray] = []  # audio from sample self._offset on
        self._offset = 0
        self.done = 0  # frames predicted so far
        self._parts: list[np.ndarray] = []
        self._tail = np.zeros((0, 0), np.float32)  # the last block's prediction of the next one's start
        self._active = 0  # 32 ms chunks of speech in the predicted blocks
        self._chunks = 0

    def _sample(self, frame: int) -> int:
        return int(round(frame / self.fps * SAMPLE_RATE))

    def push(self, samples: np.ndarray) -> None:
        """Append ``(S,)`` float32 samples; predicts every block whose audio and context have all arrived."""
        samples = np.asarray(samples, np.float32).reshape(-1)
        if len(samples) == 0:
            return
        self._pieces.append(samples)
        self.held += len(samples)
        self.received += len(samples)
        while self.transcript is None:
            end = self.done + self.block
            if self._sample(end + self.context) > self.received:
                break
            self._predict(end, end + self.context, final=False)

    def finish(self, num_frames: int | None = None) -> np.ndarray:
        """Expressions ``(T, K_exp)`` of all the audio pushed; ``T`` = ``num_frames`` (default
        :func:`nvp.windows.num_video_frames` of its duration)."""
        from nvp.windows import num_video_frames

        if self.received == 0:
            raise NvpError("expected audio to predict expressions from, found none")
        total = num_video_frames(self.received / SAMPLE_RATE, self.fps) if num_frames is None else num_frames
        if total > self.done or not self._parts:
            self._predict(total, total, final=True)
        out = np.concatenate(self._parts)[:total]
        self._parts = [out]
        return out

    def has_speech(self) -> bool:
        """Whether the audio predicted so far holds speech (:func:`nvp.vad.speech_activity`)."""
        from nvp.vad import enough_speech

        return enough_speech(self._active, self._chunks)

    def _predict(self, end: int, reach: int, final: bool) -> None:
        """Predicts frames ``[done, end)`` from the audio of frames ``[done - context, reach)`` (the rest of
        the audio when ``final``), and forgets the audio no later block reads."""
        from nvp.person import predict_expressions
        from nvp.vad import CHUNK, SPEECH_THRESHOLD, speech_probability

        first = max(0, self.done - self.context)
        start = self._sample(first)
        audio = np.concatenate(self._pieces) if len(self._pieces) > 1 else self._pieces[0]
        stop = self.held if final else self._sample(reach) - self._offset
        seg = audio[start - self._offset : stop]
        expr = predict_expressions(
            seg, SAMPLE_RATE, self.fps, self.style, self.net, reach - first, transcript=self.transcript
        )
        new = expr[self.done - first :]  # frames done … reach
        f = min(len(self._tail), len(new))  # the previous block's prediction of the first of them
        if f:  # faded into this block's, as the features' chunks are (no jump at the edge)
            w = np.arange(1, f + 1, dtype=np.float32)[:, None] / (f + 1)
            new[:f] = self._tail[:f] + w * (new[:f] - self._tail[:f])
        self._parts.append(new[: end - self.done])
        self._tail = new[end - self.done : end - self.done + self.context // 2].copy()
        # speech in this block's own audio (the context's is counted with its own block)
        p = speech_probability(seg, SAMPLE_RATE)
        lo = (self._sample(self.done) - start) // CHUNK
        hi = len(p) if final else (self._sample(end) - start) // CHUNK
        self._active += int(np.count_nonzero(p[lo:hi] >= SPEECH_THRESHOLD))
        self._chunks += max(0, hi - lo)
        self.done = end
        keep = self._sample(max(0, end - self.context))  # the next block's context starts here
        self._pieces = [] if final else [audio[keep - self._offset :].copy()]  # not a view of all of it
        self.held = len(self._pieces[0]) if self._pieces else 0
        self._offset = keep
        del audio, seg, expr, p
        release_freed_memory()  # each block's temporaries, kept, fragment what the next one allocates

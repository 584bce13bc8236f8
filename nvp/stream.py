"""Expressions from audio that arrives in pieces (``nvp live``): a frame is predicted as soon as its audio
and a short look-ahead are there.

Whole-file prediction (:func:`nvp.person.predict_expressions`) sees all the audio. Live, frame ``i`` (at
``i / fps`` s) can only use the audio up to ``i / fps + lookahead_s``: the network's feature window reaches
0.14 s ahead (8 frames of 50 Hz features), the expression filter 3 video frames more (whose windows
reach 0.14 s further), the voice-activity ramp starts 0.12 s before speech, and the phoneme recogniser
(a conformer that attends over its input) needs some audio after the last feature it is asked for. Each
step runs features, network and voice activity on the last ``context_s`` seconds before the first new
frame plus everything after it, so the cost per step does not grow with the stream's length (the opening
model's Whisper features read only the last :data:`OPENING_CONTEXT_S` of it).
"""

from __future__ import annotations

import numpy as np

from nvp.audio2exp import Audio2ExpressionNet, network_outputs
from nvp.person import PersonStyle, apply_style, opening_outputs, speech_features
from nvp.rounding import rounded_share

SAMPLE_RATE = 16000
LOOKAHEAD_S = 0.4
"""Audio after a frame's time that must have arrived before the frame is predicted (see the module
docstring; ``scripts/bench/live.py`` measures what it costs against whole-file prediction)."""
CONTEXT_S = 4.0
"""Audio before the first new frame that each step re-reads (the recogniser's and the filter's past).
Streamed in 0.2 s steps with a 0.4 s look-ahead, the inner-lip gap of two test clips
(pcavs__681600002_av, minimates__driving) correlates with whole-file prediction at 0.89 / 0.93 with 1 s of
context, 0.93 / 0.96 with 4 s, 0.95 / 0.97 with 8 s, for 90 / 175 / 300 ms of compute per second of audio
(one core, another job running)."""


OPENING_CONTEXT_S = 2.0
"""Audio before the first new frame that each step re-reads for the opening model's Whisper features (its
read-out looks 0.16 s around a frame, and Whisper costs in proportion to the audio it reads; a person fitted
with the earlier ``"phonetic"`` opening model takes them from the recogniser's pass over ``CONTEXT_S``).
``scripts/bench/live.py`` on a 512² person and a 19.8 s clip, streamed vs whole-file inner-lip gap
correlation / compute per second of audio: 4 s (= CONTEXT_S) 0.963 / 160-167 ms, 2 s 0.959 / 134-148 ms,
1 s 0.948 / 123-139 ms (the earlier phonetic model: 0.960 / 100-107 ms)."""


class ExpressionStream:
    """Feed mono 16 kHz audio with :meth:`push` as it arrives; each call returns the expressions
    ``(n, K_exp)`` of the frames that became ready (in order, none twice); :meth:`finish` returns the rest
    when the audio has ended. ``done`` counts the frames returned so far."""

    def __init__(
        self,
        style: PersonStyle,
        net: Audio2ExpressionNet,
        fps: float,
        lookahead_s: float = LOOKAHEAD_S,
        context_s: float = CONTEXT_S,
        opening_context_s: float = OPENING_CONTEXT_S,
    ) -> None:
        self.style, self.net, self.fps = style, net, float(fps)
        self.lookahead_s, self.context_s = lookahead_s, context_s
        self.opening_context_s = min(opening_context_s, context_s)
        self._audio = np.zeros(0, np.float32)
        self._offset = 0  # stream sample index of self._audio[0]
        self.received = 0  # samples received so far
        self.done = 0

    def ready_frames(self) -> int:
        """Frames whose audio and look-ahead have arrived."""
        from nvp.windows import num_video_frames

        return num_video_frames(max(0.0, self.received / SAMPLE_RATE - self.lookahead_s), self.fps)

    def push(self, samples: np.ndarray) -> np.ndarray:
        """Append ``(S,)`` float32 samples (16 kHz mono, in [-1, 1]); expressions of the frames now ready."""
        samples = np.asarray(samples, np.float32).reshape(-1)
        self._audio = np.concatenate([self._audio, samples])
        self.received += len(samples)
        return self._predict(self.ready_frames(), final=False)

    def finish(self) -> np.ndarray:
        """Expressions of every frame not returned yet (the audio has ended)."""
        from nvp.windows import num_video_frames

        return self._predict(num_video_frames(self.received / SAMPLE_RATE, self.fps), final=True)

    def _predict(self, end: int, final: bool) -> np.ndarray:
        from nvp.vad import voice_activity
        from nvp.windows import frame_windows

        k_dim = self.style.rest_expression.shape[0]
        if end <= self.done:
            return np.zeros((0, k_dim), np.float32)
        first = max(0, self.done - int(round(self.context_s * self.fps)))
        start = int(round(first / self.fps * SAMPLE_RATE))
        # forget audio no later step can need (steps only move forward)
        if start > self._offset:
            self._audio = self._audio[start - self._offset :]
            self._offset = start
        seg = self._audio[start - self._offset :]
        # the filter looks 3 frames ahead of the last frame asked for: predict those too (edge-padded past
        # the audio's end only when the stream has ended)
        f = self.net.cfg.filter_window
        n = end - first + (0 if final else f - f // 2 - 1)
        # the opening model's own features (Whisper) read only the last opening_context_s before the
        # first new frame: from frame k of this step on
        k = max(0, self.done - first - int(round(self.opening_context_s * self.fps)))
        at = int(round(k / self.fps * SAMPLE_RATE))
        feats, opening_feats, opening_at = speech_features(seg, SAMPLE_RATE, self.style, opening_from=at)
        skip = int(round(opening_at / SAMPLE_RATE * self.fps))  # k, or 0: features from the recogniser's pass
        opening = opening_outputs(self.style, opening_feats, self.fps, n, first=skip)
        windows = frame_windows(feats, self.fps, num_frames=n)
        audio_exp, closure = network_outputs(self.net, [windows])
        voice = voice_activity(seg, SAMPLE_RATE, self.fps, n)
        rounded = rounded_share(windows) if self.style.hears_rounding else None
        expr = apply_style(
            self.style, audio_exp, closure, voice, opening=opening, fps=self.fps, rounded=rounded
        )[self.done - first : end - first]
        self.done = end
        return expr

"""Warnings about some samples of a batch, which a caller can reword with its own names for them, and about one frame
of a recording, which a caller can group by kind.

A library call sees a batch and its sample indices; the command line sees a recording and its frame numbers.
:class:`SampleWarning` keeps which samples a message is about apart from its wording, so
``evlatcorr correct`` says "frame 12" where the search said "sample 0". :class:`FrameWarning` keeps what happened
(its kind) apart from the frame's figures, so a recording whose frames all lack events gets one line of it and a count,
not one line a frame.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["FrameWarning", "SampleWarning"]


class SampleWarning(UserWarning):
    """A warning about the samples ``samples`` of a batch.

    Args:
        kind: what happened, one short name per message template (a caller may group warnings by it).
        samples: the batch indices the message is about.
        text: the message, with ``{which}`` where the samples are named (and ``{its}`` for "its" or "their").
        summary: what happened without any sample's figures, e.g. to say it of several frames at once.

    ``str()`` names the samples by their indices; :meth:`naming` by names the caller gives.

    Raises:
        ValueError: without samples, or a text without ``{which}``.

    Example:
        >>> w = SampleWarning("fallback", [0, 2], "{which}: no clear minimum", "no clear minimum")
        >>> str(w)
        'samples [0, 2]: no clear minimum'
        >>> w.naming(["frame 7", "frame 8", "frame 9"])
        'frames 7, 9: no clear minimum'
        >>> str(SampleWarning("fallback", [1], "{which}: {its} latency is 0 us", "the fallback"))
        'sample 1: its latency is 0 us'
    """

    def __init__(self, kind: str, samples: Sequence[int], text: str, summary: str) -> None:
        if not samples or "{which}" not in text:
            raise ValueError(f"a SampleWarning names one sample or more, in its text's {{which}}; got samples "
                             f"{list(samples)} and text {text!r}")
        # the arguments are the exception's args, so it pickles (e.g. across processes) as it was made
        super().__init__(kind, tuple(int(i) for i in samples), text, summary)
        self.kind, self.samples, self.text, self.summary = kind, tuple(int(i) for i in samples), text, summary

    def __str__(self) -> str:
        which = (f"sample {self.samples[0]}" if len(self.samples) == 1
                 else f"samples {list(self.samples)}")
        return self._text(which)

    def naming(self, names: Sequence[str]) -> str:
        """The message with sample ``i`` called ``names[i]`` (names such as ``"frame 12"``: several are joined as
        ``"frames 12, 14"``)."""
        if max(self.samples) >= len(names):
            raise ValueError(f"naming needs a name for each of samples {list(self.samples)}, got {len(names)}")
        chosen = [names[i] for i in self.samples]
        nouns = {name.split(" ", 1)[0] for name in chosen}
        if len(chosen) > 1 and len(nouns) == 1 and all(" " in name for name in chosen):
            noun = nouns.pop()
            which = f"{noun}s " + ", ".join(name.split(" ", 1)[1] for name in chosen)
        else:
            which = ", ".join(chosen)
        return self._text(which)

    def _text(self, which: str) -> str:
        return self.text.format(which=which, its="its" if len(self.samples) == 1 else "their")


class FrameWarning(UserWarning):
    """A warning about one frame of a recording, of a kind a caller may group (e.g. one line for many frames).

    Args:
        kind: what happened, one short name per message template.
        frame: the frame's number in its recording.
        text: the whole message, the frame's figures included.
        summary: what happened without the frame's figures, said of one frame or several ("no events in the exposure").

    ``str()`` is ``text``.

    Example:
        >>> w = FrameWarning("no_events", 7, "rec.h5: frame 7 has no events inside its exposure [0, 20000) us",
        ...                  "no events inside the exposure")
        >>> str(w), w.kind, w.frame
        ('rec.h5: frame 7 has no events inside its exposure [0, 20000) us', 'no_events', 7)
    """

    def __init__(self, kind: str, frame: int, text: str, summary: str) -> None:
        # the arguments are the exception's args, so it pickles (e.g. across processes) as it was made
        super().__init__(kind, int(frame), text, summary)
        self.kind, self.frame, self.text, self.summary = kind, int(frame), text, summary

    def __str__(self) -> str:
        return self.text

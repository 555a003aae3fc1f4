"""Warnings about some samples of a batch, which a caller can reword with its own names for them, and about one frame
of a recording, which a caller can group by kind.

A library call sees a batch and its sample indices; the command line sees a recording and its frame numbers.
:class:`SampleWarning` keeps which samples a message is about apart from its wording, so
``evlatcorr correct`` says "frame 12" where the search said "sample 0". :class:`FrameWarning` keeps what happened
(its kind) apart from the frame's figures, so a recording whose frames all lack events gets one line of it and a count,
not one line a frame.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from types import FrameType

import torch

__all__ = ["FrameWarning", "SampleWarning", "user_stacklevel"]

# frames inside these folders are not the user's: a warning raised deep in a corrector's call (under nn.Module's
# __call__, torch.compiler.disable's wrapper, an adapter) points at the first frame outside them
_PACKAGE = os.path.dirname(os.path.abspath(__file__))
_LIBRARY_PACKAGES = ("evlatcorr", "adapters", "torch")
_LIBRARY_DIRS = tuple(os.path.join(folder, "") for folder in
                      (_PACKAGE, os.path.join(os.path.dirname(_PACKAGE), "adapters"), os.path.dirname(torch.__file__)))


def user_stacklevel() -> int:
    """The ``stacklevel`` of :func:`warnings.warn`, called from the function that warns, that points at the first
    caller outside evlatcorr, its adapters and torch: the user's line, however deep the call that warns.

    Example:
        >>> import warnings
        >>> def check():
        ...     warnings.warn("checked", stacklevel=user_stacklevel())
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     check()
        >>> caught[0].filename == __file__ or caught[0].filename.startswith("<doctest")
        True
    """
    frame, level = sys._getframe(1), 1  # the function that warns: level 1 of warnings.warn
    while frame is not None and _in_library(frame):
        frame, level = frame.f_back, level + 1
    return level


def _in_library(frame: FrameType) -> bool:
    filename = frame.f_code.co_filename
    if filename.startswith("<"):  # generated code, e.g. a dataclass's __init__: the library's if it is a method of ours
        owner = type(frame.f_locals.get("self")).__module__
        return owner.split(".")[0] in _LIBRARY_PACKAGES
    return os.path.abspath(filename).startswith(_LIBRARY_DIRS)


class SampleWarning(UserWarning):
    """A warning about the samples ``samples`` of a batch.

    Args:
        kind: what happened, one short name per message template (a caller may group warnings by it).
        samples: the batch indices the message is about.
        text: the message, with ``{which}`` where the samples are named (and ``{its}`` for "its" or "their").
        summary: what happened without any sample's figures, e.g. to say it of several frames at once.
        noun: what ``str()`` calls a sample (a stream's warnings name its frames: ``"frame"``).

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
        >>> str(SampleWarning("fallback", [12, 13], "{which}: no clear minimum", "no clear minimum", noun="frame"))
        'frames [12, 13]: no clear minimum'
    """

    def __init__(self, kind: str, samples: Sequence[int], text: str, summary: str, noun: str = "sample") -> None:
        if not samples or "{which}" not in text:
            raise ValueError(f"a SampleWarning names one sample or more, in its text's {{which}}; got samples "
                             f"{list(samples)} and text {text!r}")
        # the arguments are the exception's args, so it pickles (e.g. across processes) as it was made
        super().__init__(kind, tuple(int(i) for i in samples), text, summary, noun)
        self.kind, self.samples, self.text, self.summary = kind, tuple(int(i) for i in samples), text, summary
        self.noun = noun

    def __str__(self) -> str:
        which = (f"{self.noun} {self.samples[0]}" if len(self.samples) == 1
                 else f"{self.noun}s {list(self.samples)}")
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

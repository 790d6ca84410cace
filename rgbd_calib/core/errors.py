"""One error family for every user-facing failure.

The CLI prints ``str(error)`` as a single line and exits non-zero; messages therefore say
what is wrong, which file, and what to do. An error about a file whose format
docs/formats.md documents ends with a pointer to that section (:func:`format_link`).
"""

from __future__ import annotations

FORMATS_DOC = "docs/formats.md"
# words that name a documented file in a message -> its section of docs/formats.md
FORMAT_SECTIONS: tuple[tuple[tuple[str, ...], str], ...] = (
    (("rig.yaml", "rig file"), "#rigyaml"),
    (("Nodes.csv", "Edges.csv", "camera poses CSV"), "#thesis-pose-graph-csvs"),
    (("extrinsics.yaml", "extrinsics file", "--fix file", "--init"), "#calibration-output"),
    (("ground_truth.yaml",), "#synthetic-ground-truth"),
    (("board file", "board yaml"), "#board-file-added"),
)


def format_link(message: str, default_section: str | None = None) -> str | None:
    """The docs/formats.md section a message is about (the first file it names, else
    ``default_section``), or None."""
    lowered = message.lower()
    for words, section in FORMAT_SECTIONS:
        if any(w.lower() in lowered for w in words):
            return FORMATS_DOC + section
    return FORMATS_DOC + default_section if default_section else None


class RgbdCalibError(Exception):
    """Base class of every error a user can cause (bad files, bad options, bad data)."""

    format_section: str | None = None  # the formats.md section of this kind of error

    def __str__(self) -> str:
        text = Exception.__str__(self)  # not KeyError's repr (UnknownCameraError)
        link = format_link(text, self.format_section)
        if FORMATS_DOC in text:  # a message that names the doc: point it at the section
            if link and FORMATS_DOC + "#" not in text:
                text = text.replace(FORMATS_DOC, link, 1)
            return text
        return f"{text} (format: {link})" if link else text


class ConfigError(RgbdCalibError):
    """A YAML/CSV/config file is malformed or inconsistent."""


class BoardError(ConfigError):
    """A board definition is invalid (duplicate ids, mirrored winding, ...)."""

    format_section = "#board-file-added"


class DatasetError(RgbdCalibError):
    """A recorded dataset folder is unreadable or inconsistent with its rig.yaml."""

    format_section = "#recorded-rgb-d-set-folder-form"


class CalibrationError(RgbdCalibError):
    """Nothing valid can be calibrated from the given data."""


class UnknownCameraError(RgbdCalibError, KeyError):
    """A camera name that is not among a result's cameras; the message lists the valid names.
    A ``KeyError`` too, so ``except KeyError`` written before it existed still catches it."""

"""Re-export of topocut.tasks.letters (letter goals of cream writing)."""
from topocut.tasks.letters import (  # noqa: F401
    BEAD,
    LETTER_ASPECT,
    LETTERS,
    layout,
    letter_points,
    polyline_length,
    resample_polyline,
    word_goal,
)

"""The base of every recipe model.

Recipe models subclass the engine's settings base (:class:`calstation.engine.settings.Settings`:
unknown keys are errors, values finite), so that the engine settings a recipe nests
(``calibration.shape``, ``qa``, the fixture geometries) and the recipe's own sections validate
alike.
"""

from __future__ import annotations

from calstation.engine.settings import Settings

Model = Settings
"""Base of the recipe models: the engine settings' base, so that both nest alike."""

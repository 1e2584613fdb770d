"""Live ``set`` requests: check, apply, put on trial, roll back, save.

A change is validated (:mod:`kmead.config.schema`), refused when it would contradict the
running state (``problem``), applied by the host's ``reconfigure(key, value)``, and then on
trial (:mod:`kmead.run.rollback`): if most of the next frames fail, the old value returns
with an ``error`` event. ``save_config`` writes the overlay; for a key on trial it writes the
value before it, and writes again once the trial passes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from kmead.config.layers import LIVE_KEYS, Config, ConfigError, is_live, overlay_doc, save_overlay
from kmead.run.rollback import ChangeGuard

__all__ = ["LiveSettings"]

log = logging.getLogger("kmead")


class LiveSettings:
    """The live keys of one running host (the daemon, the fusion node).

    ``reconfigure(key, value)``: make the running parts follow ``cfg`` after ``key``
    changed (raises on failure); ``problem(key, value)``: why a valid value cannot apply
    now, or None; ``event(level, text)``: report a rollback.
    """

    def __init__(self, cfg: Config, reconfigure: Callable[[str, Any], None],
                 event: Callable[[str, str], None],
                 problem: Callable[[str, Any], str | None] = lambda key, value: None) -> None:
        self.cfg = cfg
        self.reconfigure = reconfigure
        self.event = event
        self.problem = problem
        self.guard = ChangeGuard()
        self._resave = False  # save_config ran while a change was on trial

    def set(self, key: str, value: Any, remote: bool = False) -> Any:
        """Validate and apply one key live (``ConfigError``/``ValueError`` if not allowed);
        ``remote``: the value came over the network. Returns the stored value."""
        old = self.cfg.get(key)  # ConfigError for an unknown key
        if not is_live(key):
            raise ConfigError(f"control: key {key!r} cannot change while running "
                              f"(live keys: {', '.join(sorted(LIVE_KEYS))}); "
                              "save it and restart kmead")
        v = self._apply(key, value, old, remote)
        # Every live change goes on trial, not only the detector's and the estimator's: a
        # filter value inside its range once made every frame fail.
        self.guard.begin(key, old, v)
        log.info("set %s = %r", key, v)
        return v

    def _apply(self, key: str, value: Any, old: Any, remote: bool = False) -> Any:
        v = self.cfg.set(key, value, where="control", remote=remote)
        problem = self.problem(key, v)
        if problem:
            self.cfg.set(key, old, where="control")
            raise ConfigError(f"control: {problem}")
        try:
            self.reconfigure(key, v)
        except Exception as e:
            self.cfg.set(key, old, where="control")
            try:
                self.reconfigure(key, old)
            except Exception as e2:  # the old value worked before; say so if it does not now
                log.error("control: key %r: restoring the previous value: %s", key, e2)
            raise ValueError(f"control: key {key!r}: {e}") from None
        return v

    def judge(self, ok: bool) -> None:
        """One frame's outcome for the change on trial; undo it if it broke the frames.

        A save_config during the trial wrote the previous value; once the trial passes the
        overlay is written again with the new one (after a rollback it is right as it is).
        """
        pending = bool(self.guard.trials)
        condemned = self.guard.frame(ok)
        if pending and not self.guard.trials and self._resave:
            self._resave = False
            if not condemned:
                try:
                    self.save()
                except Exception as e:
                    self.event("error", f"save_config after the trial: {e}")
        for trial in condemned:
            try:
                self._apply(trial.key, trial.old, trial.new)
            except Exception as e:
                self.event("error", f"rollback of {trial.key} failed: {e}")
                continue
            self.event("error", f"set {trial.key} rolled back: {trial.failures} of the "
                                f"{trial.frames} frames after it failed; the previous "
                                f"value is back")

    def save(self, path: str | None = None) -> dict:
        """Write the overlay (``save_config``); a key on trial keeps its previous value."""
        doc = overlay_doc(self.cfg)
        held = []
        for key in list(self.guard.trials):
            section, _, name = key.partition(".")
            old = self.guard.trials[key].old
            if key == "robots":
                doc.pop("robots", None)
                if old != self.cfg.base.get("robots"):
                    doc["robots"] = old
            else:
                doc.get(section, {}).pop(name, None)
                if self.cfg.base.get(section, {}).get(name) != old:
                    doc.setdefault(section, {})[name] = old
            held.append(key)
        doc = {k: v for k, v in doc.items() if v != {}}
        p, doc = save_overlay(self.cfg, path, doc)
        self._resave = bool(held)
        if held:
            log.info("save_config: %s on trial; saved the previous value for now (saved "
                     "again when the trial passes)", ", ".join(held))
        keys = sorted(f"{s}.{k}" for s, t in doc.items() if s != "robots" for k in t)
        if "robots" in doc:
            keys.append("robots")
        log.info("configuration overlay saved: %s (%s)", p, ", ".join(keys) or "no changes")
        return {"path": str(p), "keys": keys, "held": held}

    def settle(self) -> None:
        """At shutdown: a change on trial whose frames so far mostly succeeded counts as
        passed, so a save_config made during its trial gets the new value."""
        trials = list(self.guard.trials.values())
        if not (trials and self._resave):
            return
        t = trials[0]
        self.guard.trials.clear()
        self._resave = False
        if t.frames and t.failures <= self.guard.ratio * t.frames:
            try:
                self.save()
            except Exception as e:
                log.error("save_config at shutdown: %s", e)

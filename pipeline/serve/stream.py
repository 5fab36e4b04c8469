"""The render loop of a session: one thread that turns rig versions into frames for every viewer.

It sleeps until the session's version moves, then consumes `Session.frames()` and hands each frame
to the subscribers. When a newer version exists it stops consuming the frames of the old one at
once (a progressive renderer is not left refining a stale rig), so edits made during a render are
coalesced and the next frame shows the latest of them. Subscribers keep only the newest frame
they were handed (`Viewer`), so a slow client skips frames instead of queueing them.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Protocol

from pipeline.serve.session import Frame, Session

log = logging.getLogger("relight")


class Subscriber(Protocol):
    """A frame consumer (a WebSocket client)."""

    def wants_groups(self) -> bool:
        """Whether it shows a light-group view (frames then carry the group images)."""

    def deliver(self, frame: Frame) -> None:
        """Take a frame; called on the render thread, so it must return at once."""

    def failed(self, version: int, message: str) -> None:
        """Rendering `version` failed with this one-line message (the session goes on)."""


class FrameStream:
    """The render thread of one session.

    Attributes:
        latest: the newest frame rendered (None before the first).
        error: the last render failure's message for the version it failed on, or None.
    """

    def __init__(self, session: Session):
        self.session = session
        self.latest: Frame | None = None
        self.error: tuple[int, str] | None = None
        self._subscribers: list[Subscriber] = []
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="relight-serve-render", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        with self.session.changed:
            self._stopped = True
            self.session.changed.notify_all()
        self._thread.join()

    def subscribe(self, subscriber: Subscriber) -> Callable[[], None]:
        """Add a subscriber (handed the latest frame at once); returns its unsubscribe function."""
        with self.session.changed:
            self._subscribers.append(subscriber)
            latest = self.latest
            self.session.changed.notify_all()  # it may want light groups the latest frame lacks
        if latest is not None:
            subscriber.deliver(latest)

        def unsubscribe() -> None:
            with self.session.changed:
                if subscriber in self._subscribers:
                    self._subscribers.remove(subscriber)

        return unsubscribe

    def poke(self) -> None:
        """Wake the loop: a subscriber's view changed (it may now need light groups)."""
        with self.session.changed:
            self.session.changed.notify_all()

    def wait_frame(self, timeout: float = 120.0) -> Frame:
        """The final frame of the session's version at the time of the call (or a later one).

        Raises:
            RuntimeError: rendering that version failed (its message), or `timeout` seconds passed.
        """
        with self.session.changed:
            version = self.session.version
            self.session.changed.notify_all()
            done = self.session.changed.wait_for(
                lambda: (
                    self._stopped
                    or (self.latest is not None and self.latest.final and self.latest.version >= version)
                    or (self.error is not None and self.error[0] >= version)
                ),
                timeout,
            )
            if self.error is not None and self.error[0] >= version:
                raise RuntimeError(self.error[1])
            if not done or self.latest is None:
                raise RuntimeError(f"no frame of version {version} within {timeout:g} s")
            return self.latest

    def _needs_work(self) -> bool:
        latest, error = self.latest, self.error
        done = max(latest.version if latest is not None and latest.final else -1, error[0] if error else -1)
        if done < self.session.version:
            return True
        return (
            latest is not None
            and latest.version == done
            and latest.groups is None
            and any(s.wants_groups() for s in self._subscribers)
        )

    def _run(self) -> None:
        while True:
            with self.session.changed:
                self.session.changed.wait_for(lambda: self._stopped or self._needs_work())
                if self._stopped:
                    return
                groups = any(s.wants_groups() for s in self._subscribers)
                version = self.session.version
            try:
                frames = self.session.frames(groups=groups)
                for frame in frames:
                    self._publish(frame)
                    if self.session.version != frame.version:
                        frames.close()  # a newer edit: stop refining a stale rig
                        break
            except Exception as error:  # a render failure must not end the session
                log.exception("render of version %d failed", version)
                with self.session.changed:
                    self.error = (version, f"render failed: {type(error).__name__}: {str(error).splitlines()[0]}")
                    self.session.changed.notify_all()
                    subscribers = list(self._subscribers)
                for subscriber in subscribers:
                    subscriber.failed(version, self.error[1])

    def _publish(self, frame: Frame) -> None:
        with self.session.changed:
            self.latest = frame
            self.session.changed.notify_all()
            subscribers = list(self._subscribers)
        for subscriber in subscribers:
            subscriber.deliver(frame)

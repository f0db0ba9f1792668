"""The pygame window of the human-play game: key events in, `GameSession.frame()` out.

All game logic lives in `snac_jax.human.game`; this loop only translates events. With
`SDL_VIDEODRIVER=dummy` it runs headless, and `script` feeds it key presses through pygame's own
event queue (tests drive whole episodes this way).
"""

from __future__ import annotations

from collections.abc import Sequence

from snac_jax.human.game import NEXT_EPISODE_KEYS, QUIT_KEYS, GameSession

# What tells SDL (pygame's window layer) where to draw on Linux and the other X11/Wayland systems.
DISPLAY_VARIABLES = ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")


def check_display(environ=None, platform: str | None = None) -> None:
    """A one-line `ValueError` where no window can be shown: on Linux and the BSDs, none of
    `DISPLAY_VARIABLES` set (a shell over ssh, a container, CI). Why: there SDL finds no video
    device and pygame waits for events that never come, so the command would hang silently.
    macOS and Windows always have their own display."""
    import os
    import sys

    environ = os.environ if environ is None else environ
    platform = sys.platform if platform is None else platform
    if platform.startswith(("darwin", "win32", "cygwin")) or any(environ.get(v) for v in DISPLAY_VARIABLES):
        return
    raise ValueError(
        "no display to open the game window on: set DISPLAY or WAYLAND_DISPLAY (a desktop session, "
        "ssh -X), or SDL_VIDEODRIVER=dummy to run it without a window"
    )


def run_window(
    session: GameSession, *, max_episodes: int | None = None, script: Sequence[str] | None = None, fps: int = 30
) -> int:
    """Play until the window is closed, a quit key is pressed, or `max_episodes` episodes have
    ended and the player presses enter. Returns the number of episodes recorded.

    `script`: key names posted as key presses before the loop starts; the loop then stops when
    the script is used up (so a scripted run never waits for a person).
    """
    import os

    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import pygame

    check_display()
    pygame.display.init()  # display only: no audio device is needed (or wanted headless)
    try:
        frame = session.frame()
        screen = pygame.display.set_mode((frame.shape[1], frame.shape[0]))
        pygame.display.set_caption(f"SNAC: {session.task} ({session.mode} mode)")
        if script is not None:
            for name in script:
                code = pygame.key.key_code(name)
                pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=code, mod=0, unicode="", scancode=0))
        clock = pygame.time.Clock()
        running, dirty = True, True
        while running:
            events = pygame.event.get()
            for event in events:
                if event.type == pygame.QUIT:
                    running = False
                elif event.type == pygame.KEYDOWN:
                    name = pygame.key.name(event.key)
                    if name in QUIT_KEYS:
                        running = False
                    elif session.over and name in NEXT_EPISODE_KEYS:
                        if max_episodes is not None and len(session.records) >= max_episodes:
                            running = False
                        else:
                            session.new_episode()
                            dirty = True
                    else:
                        dirty |= session.press(name)
                if not running:
                    break
            if dirty:
                frame = session.frame()
                surface = pygame.surfarray.make_surface(frame.swapaxes(0, 1))
                screen.blit(surface, (0, 0))
                pygame.display.flip()
                dirty = False
            if script is not None and not events and not pygame.event.peek():
                running = False
            clock.tick(fps)
    finally:
        pygame.quit()
    return len(session.records)

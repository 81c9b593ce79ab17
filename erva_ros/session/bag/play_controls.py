"""Pause and resume of `erva bag play` / `erva replay`: a key on a terminal, and signals.

* On a terminal, the space bar toggles pause / resume, as in ``ros2 bag play``
  (``--disable-keyboard-controls`` turns it off).  The terminal is put in cbreak mode
  (keys arrive one by one, not echoed; Ctrl-C still interrupts) and restored on exit.
* From another process: ``kill -USR1 <pid>`` pauses, ``kill -USR2 <pid>`` resumes.  Two
  signals rather than one toggle, so a script knows the state it asked for (a signal
  sent twice before it is handled is delivered once), and repeating one is harmless.

Each pause and resume that takes effect is reported on stderr with the number of
messages published until then.
"""

import os
import select
import signal
import sys
import termios
import threading
from typing import Callable, Optional, TextIO

#: The keys of the player (as rosbag2's: SPACE toggles).
PAUSE_KEY = ' '
PAUSE_SIGNAL, RESUME_SIGNAL = signal.SIGUSR1, signal.SIGUSR2


class KeyboardControls:
    """Read single keys from a terminal in a thread; ``on_key(key)`` for each."""

    def __init__(self, on_key: Callable[[str], None], stream: Optional[TextIO] = None):
        self.on_key = on_key
        self.stream = sys.stdin if stream is None else stream
        self._saved = None
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def start(self) -> bool:
        """Start when the stream is a terminal; return whether it did."""
        try:
            if not self.stream.isatty():
                return False
            import termios
            import tty
            fd = self.stream.fileno()
            self._saved = termios.tcgetattr(fd)
            tty.setcbreak(fd)
        except (OSError, ValueError, ImportError):
            return False
        self._thread = threading.Thread(target=self._read, args=(fd,), daemon=True,
                                        name='keyboard')
        self._thread.start()
        return True

    @property
    def active(self) -> bool:
        """Return whether keys are being read."""
        return self._thread is not None and not self._stop.is_set()

    def _read(self, fd: int) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([fd], [], [], 0.1)
            if ready:
                data = os.read(fd, 32)
                if not data:
                    return
                for key in data.decode(errors='ignore'):
                    self.on_key(key)

    def close(self) -> None:
        """Stop reading and give the terminal its settings back."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._saved is not None:
            termios.tcsetattr(self.stream.fileno(), termios.TCSADRAIN, self._saved)
            self._saved = None


class PlayControls:
    """Connect a player's pause and resume to the keyboard and to SIGUSR1 / SIGUSR2."""

    def __init__(self, player, prog: str, keyboard: bool = True,
                 stream: Optional[TextIO] = None):
        self.player = player
        self.prog = prog
        self.out = sys.stderr if stream is None else stream
        self.keyboard = KeyboardControls(self._on_key) if keyboard else None
        self._previous = {}
        player.on_pause = self._report

    def _on_key(self, key: str) -> None:
        if key == PAUSE_KEY:
            self.player.toggle_pause()

    def _report(self, paused: bool, published: int) -> None:
        how = ('space or ' if self.keyboard is not None and self.keyboard.active else '') + \
            f'kill -USR2 {os.getpid()}'
        if paused:
            self.out.write(f'{self.prog}: paused after {published} messages ({how} '
                           'resumes)\n')
        else:
            self.out.write(f'{self.prog}: resumed after {published} messages\n')
        self.out.flush()

    def __enter__(self) -> 'PlayControls':
        self._previous = {PAUSE_SIGNAL: signal.signal(PAUSE_SIGNAL,
                                                      lambda *_: self.player.pause()),
                          RESUME_SIGNAL: signal.signal(RESUME_SIGNAL,
                                                       lambda *_: self.player.resume())}
        if self.keyboard is not None and self.keyboard.start():
            self.out.write(f'{self.prog}: space pauses and resumes, Ctrl-C stops\n')
            self.out.flush()
        return self

    def __exit__(self, *exc) -> None:
        if self.keyboard is not None:
            self.keyboard.close()
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


__all__ = ['PAUSE_KEY', 'PAUSE_SIGNAL', 'RESUME_SIGNAL', 'KeyboardControls', 'PlayControls']

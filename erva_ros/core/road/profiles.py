"""Road profiles w(t) at the tyre (m), seeded and reproducible.

Every road is sampled once on a fine time grid (1 ms) and linearly interpolated, so
``height`` is vectorised and exact to the grid wherever it is asked; the grid runs
``margin_s`` (default 5 s) past the run so that previews near the end are defined.
After the grid the last height is held.

Kinds (:data:`ROAD_KINDS`):

``paper``
    Paper §IV.B: a 1.7 Hz sine of 1 mm plus low-pass-filtered white noise at an SNR
    of 7 dB.  The paper does not give the filter; here it is a 2nd-order Butterworth
    low-pass (bilinear transform at the 1 kHz grid) with cut-off ``cutoff_hz`` =
    10 Hz, which passes both ERVA resonances (1.7 and 5.8 Hz) and removes what a
    tyre filters anyway.  The noise is scaled so that its stationary variance is
    exactly (A²/2)/10^(SNR/10) (≈ 0.316 mm RMS), using the filter's impulse-response
    energy, so the SNR does not depend on the run length; the filter starts at rest,
    so w(0) = 0 like the quarter car's initial state.
``iso8608``
    ISO 8608 random road, class A–E: displacement PSD G_d(n) = G_d(n0)·(n/n0)^-2,
    n0 = 0.1 cycle/m, G_d(n0) = 16·4^i ·1e-6 m³ (A: i = 0 … E: i = 4), spatial
    frequencies 0.011–2.83 cycle/m, random phases (spectral synthesis by inverse
    FFT), driven at ``speed_mps``.
``bump``
    One cosine bump of ``height_m`` (default 0.01 m) and ``length_m`` (default
    0.5 m), reached at ``start_s`` (default 1 s) at ``speed_mps``.
``sine``
    ``amplitude_m`` (default 1 mm) at ``freq_hz`` (default 1.7 Hz).
``recorded``
    Linear interpolation of given ``times`` (s, increasing) and ``heights`` (m), e.g. a
    CSV file of ``time_s, height_m`` rows (:func:`read_road_csv`).
"""

import codecs
from dataclasses import dataclass
import io
import math
import os
from typing import Iterator, Optional, Tuple

import numpy as np

ROAD_KINDS = ('paper', 'iso8608', 'bump', 'sine', 'recorded')
ISO_CLASSES = 'ABCDE'
#: Time grid of every road (s).
GRID_S = 1e-3
#: Default vehicle speed (m/s); only converts time to distance (paper: not stated).
DEFAULT_SPEED_MPS = 20.0


#: The largest road CSV file read (bytes): ~20 million rows, parsed in seconds.  A larger
#: file is refused before anything starts (it once took 238 s and 2.9 GB, row by row).
MAX_ROAD_FILE_BYTES = 512 * 1024 * 1024


class RoadError(ValueError):
    """A road option is invalid (one-line message)."""


def read_road_csv(path: str, what: str = 'road_file') -> np.ndarray:
    """Return the (n, 2) rows time (s), height (m) of a CSV road file; one-line RoadError.

    Rows are ``time_s, height_m`` (``,`` or ``;``; more columns are ignored); lines
    before the first numeric row are a header, ``#`` starts a comment, blank lines are
    skipped.  Parsed by numpy in one pass (10 million rows: seconds); only a file that
    fails is read again row by row, to name its first bad line.  ``what`` names the
    input in messages.
    """
    if os.path.isdir(path):
        raise RoadError(f'{what} {path!r} is a directory, not a CSV file')
    if not os.path.isfile(path):
        raise RoadError(f'{what} {path!r} does not exist')
    size = os.path.getsize(path)
    if size > MAX_ROAD_FILE_BYTES:
        raise RoadError(f'{what} {path!r} is {size / 2 ** 20:.0f} MiB; the limit is '
                        f'{MAX_ROAD_FILE_BYTES / 2 ** 20:.0f} MiB (about 20 million rows): '
                        f'cut it to the part the run drives')
    head, semicolons = _check_text(path, what)
    lines = _lines(path) if semicolons else path
    rows = None
    header = _header_lines(head.replace(';', ','))
    if header is not None:
        try:
            rows = np.loadtxt(lines, delimiter=',', comments='#', skiprows=header,
                              usecols=(0, 1), ndmin=2, dtype=float, encoding='utf-8')
        except ValueError:
            rows = None         # a bad row: found and named below
    if rows is None or not np.all(np.isfinite(rows)):
        _first_bad_row(path, what)
    if rows is None or rows.shape[0] < 2:
        raise RoadError(f'{what} {path!r} needs at least two "time_s, height_m" rows')
    back = np.flatnonzero(np.diff(rows[:, 0]) <= 0)
    if back.size:
        _unsorted_row(path, what, int(back[0]) + 1)
    return rows


#: How much of a road file is read at a time while checking it, and kept for its header.
_CHUNK, _HEAD = 1 << 24, 1 << 16


def _check_text(path: str, what: str) -> Tuple[str, bool]:
    """Check that a file is UTF-8 text without NUL; return its start and whether it has ';'.

    Read in chunks: a large file is never held whole (the parser reads the file itself).
    """
    decoder = codecs.getincrementaldecoder('utf-8')()
    head, semicolons, offset = b'', False, 0
    try:
        with open(path, 'rb') as fh:
            while True:
                chunk = fh.read(_CHUNK)
                nul = chunk.find(b'\x00')
                try:
                    if nul >= 0:
                        raise UnicodeDecodeError('utf-8', chunk, nul, nul + 1, 'NUL byte')
                    decoder.decode(chunk, final=not chunk)
                except UnicodeDecodeError as exc:
                    raise RoadError(f'{what} {path!r} is not a UTF-8 text CSV (byte '
                                    f'{offset + exc.start}: {exc.reason})') from None
                if not chunk:
                    break
                semicolons = semicolons or b';' in chunk
                if len(head) < _HEAD:
                    head += chunk[:_HEAD]
                offset += len(chunk)
    except OSError as exc:
        raise RoadError(f'{what} {path!r} cannot be read ({exc.strerror or exc})') from None
    return head.decode('utf-8', errors='ignore'), semicolons


def _lines(path: str) -> Iterator[str]:
    """Yield the lines of a file with ``;`` separators made ``,`` (for the parser)."""
    with open(path, encoding='utf-8', newline=None) as fh:
        for line in fh:
            yield line.replace(';', ',')


def _numeric_row(text: str) -> bool:
    cells = text.split(',')
    try:
        float(cells[0])
        float(cells[1])
    except (ValueError, IndexError):
        return False
    return True


def _header_lines(head: str) -> Optional[int]:
    """Return how many lines come before the first numeric row (None: none in ``head``)."""
    for n, line in enumerate(io.StringIO(head, newline=None)):   # lines as the parser's
        body = line.split('#', 1)[0].strip()
        if body and _numeric_row(body):
            return n
    return None


def _first_bad_row(path: str, what: str) -> None:
    """Raise RoadError naming the first line that is not a finite ``time_s, height_m`` row."""
    seen_row = False
    for lineno, line in enumerate(_lines(path), 1):
        body = line.split('#', 1)[0].strip()
        if not body:
            continue
        cells = [c.strip() for c in body.split(',')]
        try:
            row = [float(cells[0]), float(cells[1])]
        except (ValueError, IndexError):
            if seen_row:        # only lines before the first row may be a header
                raise RoadError(f'{what} {path}:{lineno}: expected "time_s, height_m", got '
                                f'{body[:60]!r}') from None
            continue
        if not all(math.isfinite(v) for v in row):
            raise RoadError(f'{what} {path}:{lineno}: {body[:60]!r} is not a finite '
                            f'"time_s, height_m" row')
        seen_row = True


def _unsorted_row(path: str, what: str, index: int) -> None:
    """Raise RoadError naming the line of data row ``index`` (0-based), out of time order."""
    n, previous = -1, None
    for lineno, line in enumerate(_lines(path), 1):
        body = line.split('#', 1)[0].strip()
        if not body or not _numeric_row(body):
            continue
        n += 1
        if n == index:
            raise RoadError(f'{what} {path}:{lineno}: time {body.split(",")[0].strip()} s is '
                            f'not after the row before ({previous} s): the rows must be in '
                            'strictly increasing time')
        previous = body.split(',')[0].strip()
    raise RoadError(f'{what} {path!r}: the times must be strictly increasing')


@dataclass
class Road:
    """Road height at the tyre on a fine time grid; ``height`` interpolates linearly."""

    name: str
    times: np.ndarray       # s, increasing
    heights: np.ndarray     # m
    speed_mps: float = DEFAULT_SPEED_MPS
    preview_heights: Optional[np.ndarray] = None  # what a preview sensor sees (None: heights)

    def height(self, t):
        """Return w(t) in m (scalar or array t in s)."""
        out = np.interp(t, self.times, self.heights)
        return float(out) if np.ndim(out) == 0 else out

    def preview(self, t: float, n: int, ts: float) -> np.ndarray:
        """Return the n + 1 heights w(t + k·ts), k = 0..n (m), as a preview sensor sees them.

        Element 0 is the true current height (measured at the tyre); for the paper
        road with ``preview_sees_noise=False`` the rest are the noise-free sine.
        """
        tk = t + ts * np.arange(n + 1)
        if self.preview_heights is None:
            return np.interp(tk, self.times, self.heights)
        out = np.interp(tk, self.times, self.preview_heights)
        out[0] = self.height(t)
        return out

    def distance(self, t):
        """Return the distance travelled at time t (m), at constant ``speed_mps``."""
        return self.speed_mps * np.asarray(t, dtype=float) if np.ndim(t) else \
            self.speed_mps * float(t)


def butter2_lowpass(cutoff_hz: float, fs_hz: float):
    """Return (b, a) of a 2nd-order Butterworth low-pass by the bilinear transform."""
    k = math.tan(math.pi * cutoff_hz / fs_hz)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    b0 = k * k * norm
    return (b0, 2 * b0, b0), (1.0, 2 * (k * k - 1) * norm, (1 - math.sqrt(2.0) * k + k * k) * norm)


def lfilter2(b, a, x: np.ndarray) -> np.ndarray:
    """Filter ``x`` by the biquad (b, a) from rest (direct form II transposed)."""
    y = np.empty_like(x)
    z1 = z2 = 0.0
    b0, b1, b2 = b
    _, a1, a2 = a
    for i, xi in enumerate(x.tolist()):
        yi = b0 * xi + z1
        z1 = b1 * xi - a1 * yi + z2
        z2 = b2 * xi - a2 * yi
        y[i] = yi
    return y


def _grid(duration_s: float, margin_s: float) -> np.ndarray:
    n = int(math.ceil((duration_s + margin_s) / GRID_S - 1e-9)) + 1
    return GRID_S * np.arange(n)


def _positive(name: str, value, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RoadError(f'road option {name}={value!r} is not a number') from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise RoadError(f'road option {name}={value!r} must be a '
                        f'{"non-negative" if allow_zero else "positive"} finite number')
    return v


def paper_noise(times: np.ndarray, rms_m: float, cutoff_hz: float,
                rng: np.random.Generator) -> np.ndarray:
    """Low-pass-filtered white noise with stationary RMS ``rms_m`` on the grid ``times``."""
    fs = 1.0 / GRID_S
    b, a = butter2_lowpass(cutoff_hz, fs)
    impulse = np.zeros(int(20 * fs / cutoff_hz) + 100)
    impulse[0] = 1.0
    gain = math.sqrt(float(np.sum(lfilter2(b, a, impulse) ** 2)))
    white = rng.standard_normal(times.size) * (rms_m / gain)
    white[0] = 0.0   # filter at rest and w(0) = 0
    return lfilter2(b, a, white)


@dataclass(frozen=True)
class Iso8608Lines:
    """The spectral lines an ISO 8608 profile of ``m`` grid samples is synthesised from.

    ``n`` are the spatial frequencies (cycle/m) of the ``nfft``-point FFT of the profile by
    distance, ``amp`` the cosine amplitude of each line (m; zero outside 0.011-2.83
    cycle/m), ``phase`` its random phase (rad): the line k is amp_k·cos(2π·n_k·x + phase_k).
    """

    m: int
    nfft: int
    n: np.ndarray
    amp: np.ndarray
    phase: np.ndarray


def iso8608_amplitudes(m: int, road_class: str,
                       speed_mps: float) -> Tuple[int, np.ndarray, np.ndarray]:
    """Return (nfft, n, amp): the FFT size, line frequencies and amplitudes of ``m`` samples."""
    i = ISO_CLASSES.index(road_class)
    gd_n0 = 16e-6 * 4 ** i            # m³, geometric mean of the class
    n0, n_lo, n_hi = 0.1, 0.011, 2.83  # cycle/m
    nfft = 1 << int(math.ceil(math.log2(max(m, 2))))
    dx = speed_mps * GRID_S
    n = np.fft.rfftfreq(nfft, d=dx)
    dn = n[1] - n[0]
    band = (n >= n_lo) & (n <= n_hi)
    amp = np.zeros_like(n)
    amp[band] = np.sqrt(2.0 * gd_n0 * (n[band] / n0) ** -2 * dn)
    return nfft, n, amp


def iso8608_lines(m: int, road_class: str, speed_mps: float,
                  rng: np.random.Generator) -> Iso8608Lines:
    """Return the lines of an ISO 8608 profile of ``m`` samples on the time grid.

    The phases are ``rng``'s first draw (what :func:`make_road` uses for the road of a
    seed; :mod:`erva_ros.core.road.two_track` builds its right track on them).
    """
    nfft, n, amp = iso8608_amplitudes(m, road_class, speed_mps)
    phase = rng.uniform(0.0, 2 * math.pi, n.size)
    return Iso8608Lines(m, nfft, n, amp, phase)


def profile_from_lines(lines: Iso8608Lines, phasor: np.ndarray,
                       amp: Optional[np.ndarray] = None) -> np.ndarray:
    """Return the profile Σ_k amp_k·Re(phasor_k·e^{i2π·n_k·x}) (m), starting at 0.

    ``phasor`` is e^{i·phase} for a profile of its own; ``amp`` defaults to the lines'.
    """
    amp = lines.amp if amp is None else amp
    spec = 0.5 * lines.nfft * amp * phasor
    z = np.fft.irfft(spec, lines.nfft)[:lines.m]
    return z - z[0]  # start at 0 like the quarter car's rest state


def iso8608_profile(times: np.ndarray, road_class: str, speed_mps: float,
                    rng: np.random.Generator) -> np.ndarray:
    """ISO 8608 displacement profile (m) driven at ``speed_mps`` on the time grid."""
    lines = iso8608_lines(times.size, road_class, speed_mps, rng)
    return profile_from_lines(lines, np.exp(1j * lines.phase))


def make_road(kind: str, duration_s: float, ts: float = 0.02, seed: int = 0,
              margin_s: float = 5.0, **opts) -> Road:
    """Build a road of ``kind`` covering [0, duration_s + margin_s] (see module doc).

    ``ts`` is accepted for a uniform signature (the grid is always 1 ms, finer than
    any control period); options not used by ``kind`` raise :class:`RoadError`.
    """
    if kind not in ROAD_KINDS:
        raise RoadError(f'unknown road {kind!r}; choose one of {", ".join(ROAD_KINDS)}')
    duration_s = _positive('duration_s', duration_s)
    _positive('ts', ts)
    speed = _positive('speed_mps', opts.pop('speed_mps', DEFAULT_SPEED_MPS))
    rng = np.random.default_rng(int(seed))
    t = _grid(duration_s, _positive('margin_s', margin_s, allow_zero=True))
    preview_h = None

    def take(name, default):
        return opts.pop(name, default)

    if kind == 'paper':
        amp = _positive('amplitude_m', take('amplitude_m', 1e-3))
        freq = _positive('freq_hz', take('freq_hz', 1.7))
        snr_db = float(take('snr_db', 7.0))
        cutoff = _positive('cutoff_hz', take('cutoff_hz', 10.0))
        if cutoff >= 0.5 / GRID_S:
            raise RoadError(f'road option cutoff_hz={cutoff:g} must be below '
                            f'{0.5 / GRID_S:g} Hz')
        sees_noise = bool(take('preview_sees_noise', True))
        sine = amp * np.sin(2 * math.pi * freq * t)
        rms = math.sqrt(amp ** 2 / 2 / 10 ** (snr_db / 10))
        h = sine + paper_noise(t, rms, cutoff, rng)
        preview_h = None if sees_noise else sine
        name = f'paper(seed={seed})'
    elif kind == 'iso8608':
        cls = str(take('road_class', 'C')).upper()
        if cls not in tuple(ISO_CLASSES):
            raise RoadError(f'road option road_class={cls!r}; choose one of A, B, C, D, E')
        h = iso8608_profile(t, cls, speed, rng)
        name = f'iso8608-{cls}({speed:g} m/s, seed={seed})'
    elif kind == 'bump':
        height = float(take('height_m', 0.01))
        length = _positive('length_m', take('length_m', 0.5))
        start = _positive('start_s', take('start_s', 1.0), allow_zero=True)
        x = speed * (t - start)
        inside = (x >= 0) & (x <= length)
        h = np.where(inside, 0.5 * height * (1 - np.cos(2 * math.pi * x / length)), 0.0)
        name = f'bump({height:g} m)'
    elif kind == 'sine':
        amp = _positive('amplitude_m', take('amplitude_m', 1e-3), allow_zero=True)
        freq = _positive('freq_hz', take('freq_hz', 1.7))
        h = amp * np.sin(2 * math.pi * freq * t)
        name = f'sine({freq:g} Hz, {amp * 1e3:g} mm)'
    else:  # recorded
        times = np.asarray(take('times', None), dtype=float)
        heights = np.asarray(take('heights', None), dtype=float)
        if times.ndim != 1 or times.shape != heights.shape or times.size < 2:
            raise RoadError('recorded road needs 1-D times and heights of equal length >= 2')
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(heights))):
            raise RoadError('recorded road contains non-finite times or heights')
        if np.any(np.diff(times) <= 0):
            raise RoadError('recorded road times must be strictly increasing')
        h = np.interp(t, times - times[0], heights)
        name = str(take('name', 'recorded'))
    if opts:
        raise RoadError(f'road {kind!r} does not take option(s) {", ".join(sorted(opts))}')
    return Road(name, t, h, speed, preview_h)


__all__ = ['ROAD_KINDS', 'ISO_CLASSES', 'MAX_ROAD_FILE_BYTES', 'Road', 'RoadError',
           'read_road_csv', 'make_road', 'butter2_lowpass', 'lfilter2', 'Iso8608Lines',
           'iso8608_amplitudes', 'iso8608_lines', 'profile_from_lines']

"""Every setting of the live service in one place, with defaults and the checks between them.

`flockcal serve` builds a `Settings` from its options; tests build one directly. `check()` refuses
combinations that would be unsafe (a public address with no token) with a message naming the fix.
"""

from __future__ import annotations

import ipaddress
import os
import re
from urllib.parse import parse_qs, urlsplit
from dataclasses import dataclass, field, replace
from pathlib import Path

from flockcal.server.errors import ConfigError

DEFAULT_BIRDS = 16
DEFAULT_RATE_HZ = 144.0

# Names of sensors, performers and joints travel into file names and SQL; keep them to a safe alphabet.
# Always .fullmatch: with .match the final $ lets a trailing newline through ("a\n").
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 _.\-]{0,63}$")
NAME_RULE = "1–64 letters, digits, space, _ . - (starting with a letter or digit)"
# Performer names are only ever data (never a file name): any printable text but markup and slashes,
# and none of the invisible characters that reorder or break the text around them where it is shown
# (C0/C1 controls such as U+0085, bidi overrides and isolates such as U+202E, U+2028/9, BOM, zero widths).
PERFORMER_PATTERN = (r"^[^\x00-\x1f\x7f-\x9f/\\<>\"\u00ad\u061c\u180e\u200b\u200e\u200f\u2028-\u202e"
                     r"\u2060-\u206f\ufeff\ufff9-\ufffb]{1,64}$")
PERFORMER_RULE = "1–64 characters without slashes, quotes, < >, control or invisible formatting characters"
PERFORMER_RE = re.compile(PERFORMER_PATTERN)


def performer_pattern() -> str:
    """PERFORMER_PATTERN as the API applies it (to the name stripped of surrounding white space): at least one
    character that is not white space, none outside the allowed set, white space around it."""
    allowed = PERFORMER_PATTERN[len("^[^"):PERFORMER_PATTERN.rindex("]{")]
    return rf"^\s*[^{allowed}]*[^{allowed}\s][^{allowed}]*\s*$"


def default_device(birds: int = DEFAULT_BIRDS, rate_hz: float = DEFAULT_RATE_HZ) -> str:
    """The built-in simulator: a performer doing the exercise routine, looping forever. Its line is
    emulated at 921600 baud: 16 birds at 144 Hz need more than a 115200-baud line carries."""
    return f"sim://flockcal?birds={birds}&motion=exercise&rate={rate_hz:g}&baud=921600"


def default_data_dir() -> Path:
    """Per-user data directory: $XDG_DATA_HOME/flockcal or ~/.local/share/flockcal."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "flockcal"


def is_loopback(host: str) -> bool:
    if host in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class Settings:
    device: str | None = None  # pyserial URL, or one per bird separated by commas; None = the built-in simulator
    birds: int = DEFAULT_BIRDS
    rate_hz: float | None = None  # None = whatever the tracker (or simulator default) runs at
    host: str = "127.0.0.1"
    http_port: int = 8750
    data_dir: Path = field(default_factory=default_data_dir)
    token: str | None = None  # admin: every mutating request
    read_token: str | None = None  # read-only: GET and the websocket (kiosks, dashboards)
    kiosk_token: str | None = None  # read + start/stop sessions, nothing else
    names: tuple[str, ...] | None = None  # sensor names; None = from the simulator model, else bird1..N
    publish_hz: float = 200.0  # upper bound on snapshot rate; the pipeline publishes when frames arrive
    reader_batch_s: float = 0.005  # how often the reader hands frames over (latency vs. per-batch cost)
    fit_hz: float = 30.0  # full refit (all pairs + topology + bones) rate, ≥ 30 per the issue
    tolerance_m: float = 0.005  # a joint is determined when its centre is pinned this closely (design.md §3a)
    target_m: float | None = None  # ...and calibrated (progress, done) when pinned this closely; None: tolerance/√2
    profile: str = "stage"  # how a session that names none decides it is calibrated: stage | kiosk (solver/progress.py)
    residual_hz: float = 20.0  # residual rms samples per second kept for the time series
    residual_window_s: float = 120.0  # live residual history kept in memory
    max_body_bytes: int = 64 * 1024
    cors_origins: tuple[str, ...] = ()  # CORS closed unless origins are listed
    allow_hosts: tuple[str, ...] = ()  # Host names answered besides loopback's (server/hosts.py)
    baud: int | None = None  # line speed; None: a URL's own baud= (the simulator's emulated line), else 115200
    hemisphere: str = "forward"
    ws_max_clients: int = 200
    send_buffer_bytes: int | None = 256 * 1024  # kernel send buffer per connection (bounds a stalled client's backlog)
    ws_send_timeout_s: float = 30.0  # a websocket client that takes no data for this long is dropped
    log_level: str = "info"
    scale_inches: int | None = None  # position full scale; None: 72 for the simulator (it reaches further), else the tracker's own
    fast_init: bool = False  # skip the manual's reset delays (simulators and fake trackers on a pty)
    skeletons: tuple[Path, ...] = ()  # --skeleton files: saved performers offered as session presets
    max_session_s: float | None = 7200.0  # a live session is stopped at this length (server/limits.py); None: never
    min_free_bytes: int = 500 * 2**20  # recording stops before the recordings' disk has less than this free
    max_downloads: int = 8  # take/bvh downloads built at once (server/downloads.py); one more gets 503
    download_stall_s: float = 30.0  # a download whose client takes no data this long is cut off, its slot freed
    request_deadline_s: float = 10.0  # a request must arrive whole this soon, or its connection is closed
    keep_days: float | None = None  # retention (server/retention.py): recordings of the last N days; None: all
    keep_disk_gb: float | None = None  # ...and/or a data directory under this many GB; None: no budget
    retention_interval_s: float = 60.0  # how often the pruner looks when no session stops meanwhile
    vrpn_port: int | None = None  # serve the humanoid as the VRPN tracker "flockcal" on this port (server/vrpn.py)
    osc_targets: tuple[str, ...] = ()  # send it over the VMC protocol to these HOST[:PORT] (server/vmc.py)
    osc_hz: float = 60.0  # VMC bundles a second

    @property
    def progress_target_m(self) -> float:
        """The joint-centre error at which a joint counts as calibrated: --target-mm, else --tolerance-mm / √2
        (solver.progress.default_target: bones then within the tolerance)."""
        from flockcal.solver.progress import default_target

        return default_target(self.tolerance_m) if self.target_m is None else self.target_m

    def session_profile(self, name: str | None = None):
        """How a session decides it is calibrated: the named profile (default --profile), "stage" with this
        service's tolerance and target (solver/progress.py). ValueError for an unknown name."""
        from flockcal.solver.progress import profile

        return profile(name or self.profile, self.tolerance_m, self.progress_target_m)

    @property
    def device_url(self) -> str:
        if self.device:
            return self.device
        return default_device(self.birds, self.rate_hz or DEFAULT_RATE_HZ)

    @property
    def line_baud(self) -> int:
        """Baud the driver plans the link's capacity with: --baud, else the URL's baud=, else 115200."""
        if self.baud:
            return self.baud
        query = parse_qs(urlsplit(self.device_urls[0]).query) if self.device_urls else {}
        try:
            return int(query["baud"][0])
        except (KeyError, ValueError):
            return 115200

    @property
    def device_urls(self) -> list[str]:
        return [u.strip() for u in self.device_url.split(",") if u.strip()]

    @property
    def auth_required(self) -> bool:
        return bool(self.token)

    def with_(self, **changes) -> "Settings":
        return replace(self, **changes)

    def check(self) -> "Settings":
        """Return self if usable; raise ConfigError naming the option to change otherwise."""
        if not 2 <= self.birds <= 64:
            raise ConfigError(f"--birds must be between 2 and 64, got {self.birds}")
        if self.rate_hz is not None and not 1 <= self.rate_hz <= 1000:
            raise ConfigError(f"--rate must be between 1 and 1000 Hz, got {self.rate_hz:g}")
        if not 0 <= self.http_port <= 65535:
            raise ConfigError(f"--http-port must be 0..65535, got {self.http_port}")
        if not 0 < self.tolerance_m < 1:
            raise ConfigError(f"--tolerance-mm must be between 0 and 1000 mm, got {self.tolerance_m * 1000:g}")
        if self.target_m is not None and not 0 < self.target_m <= self.tolerance_m:
            raise ConfigError(
                f"--target-mm must be above 0 and at most --tolerance-mm ({self.tolerance_m * 1000:g} mm): a joint "
                f"counts as calibrated only once it is determined; got {self.target_m * 1000:g}")
        if self.fit_hz <= 0 or self.publish_hz <= 0:
            raise ConfigError("fit and publish rates must be positive")
        if not is_loopback(self.host) and not self.token:
            raise ConfigError(
                f"--host {self.host} is reachable from other machines; give --token SECRET "
                "(and --read-token for dashboards) so only you can change sessions"
            )
        if self.max_session_s is not None and not self.max_session_s > 0:
            raise ConfigError(f"--max-session-min must be above 0 (0 turns the limit off), got {self.max_session_s / 60:g}")
        if self.min_free_bytes < 0:
            raise ConfigError("--min-free-mb must be 0 or more")
        # Under a second a slow but honest client on a poor link loses its requests; over an hour a
        # half-sent request holds its descriptor as if there were no deadline.
        if not 1 <= self.request_deadline_s <= 3600:
            raise ConfigError(f"--request-deadline-s must be from 1 to 3600 s, got {self.request_deadline_s:g}")
        if not 1 <= self.download_stall_s <= 3600:
            raise ConfigError(f"--download-stall-s must be from 1 to 3600 s, got {self.download_stall_s:g}")
        tokens = [t for t in (self.token, self.read_token, self.kiosk_token) if t]
        if len(set(tokens)) != len(tokens):
            raise ConfigError("--token, --read-token and --kiosk-token must all differ")
        for option, t in (("--token", self.token), ("--read-token", self.read_token),
                          ("--kiosk-token", self.kiosk_token)):
            # A blank or spaced token cannot travel in an Authorization header as given (HTTP trims
            # it), and twelve spaces is no secret: refuse it rather than let it guard the service.
            if t is not None and (not t.strip() or any(c.isspace() or not c.isprintable() for c in t)):
                raise ConfigError(f"{option} is blank or holds spaces or control characters; give a token of "
                                  "8 or more printable characters without spaces")
        if any(len(t) < 8 for t in tokens):
            raise ConfigError("tokens must be at least 8 characters long")
        if (self.read_token or self.kiosk_token) and not self.token:
            raise ConfigError("--read-token/--kiosk-token need an admin --token as well")
        if self.names is not None:
            if len(self.names) != self.birds:
                raise ConfigError(f"--names lists {len(self.names)} names for {self.birds} birds")
            bad = [n for n in self.names if not NAME_RE.fullmatch(n)]
            if bad:
                raise ConfigError(f"sensor name {bad[0]!r} is not allowed: use letters, digits, space, _ . -")
            if len(set(self.names)) != len(self.names):
                raise ConfigError("sensor names must be unique")
        if not 1 <= self.osc_hz <= 1000:
            raise ConfigError(f"--osc-hz must be from 1 to 1000, got {self.osc_hz:g}")
        if self.keep_days is not None and not 0 < self.keep_days <= 36500:
            raise ConfigError(f"--keep-days must be more than 0 (and at most 36500), got {self.keep_days:g}")
        if self.keep_disk_gb is not None and not 0 < self.keep_disk_gb <= 1e6:
            raise ConfigError(f"--keep-disk must be a size in GB above 0, got {self.keep_disk_gb:g}")
        return self

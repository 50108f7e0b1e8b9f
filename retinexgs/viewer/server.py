"""The viser web viewer of a trained run: one render thread per connected browser, the GUI's controls per
client, frames sent as the scene's background image.

Safety: binds 127.0.0.1 unless told otherwise; a frame that fails (junk camera from the client, a renderer
error) is logged and skipped, never raised into viser's threads, and a client that disconnects only stops
its own render thread.
"""
from __future__ import annotations

import threading
import time
from dataclasses import replace
from typing import Callable, Dict, Optional, Tuple

from retinexgs.errors import Terminated, UserError
from retinexgs.render import Camera
from retinexgs.viewer.camera import ViewerCamera, average_up, camera_to_viewer
from retinexgs.viewer.frame import FrameRenderer, FrameSettings
from retinexgs.run.render import view_camera
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree

MOVING_SCALE = 0.5   # frames rendered while the camera moves are this much smaller (when enabled)
SETTLE_SECONDS = 0.3  # no camera update for this long: render the full-resolution frame
_LABELS = {"enhanced": "enhanced", "R": "R̂ (reflectance)", "L": "L̂ (illumination, normalised)",
           "low": "low (R̂∘L̂)", "depth": "depth"}
# The white-balance dropdown: its labels and the render --white-balance form each stands for (frame.py).
WB_MODES = {"as trained": "as-trained", "auto (grey-edge)": "auto", "temperature / tint": "temp",
            "gains (or a picked neutral)": "gains"}
TEMP_SLIDER = (1500.0, 15000.0)  # K: the useful part of 1000..40000; "temp:K" at render reaches the rest


def import_viser():
    """The viser module, or a UserError saying how to install it."""
    try:
        import viser
    except ImportError:
        raise UserError('the viewer needs viser, an optional dependency: pip install "retinexgs[view]"') from None
    return viser


class _Client:
    """One browser: its GUI controls and a render thread that draws the newest camera (older requests are
    dropped, so a slow renderer never builds a backlog)."""

    def __init__(self, viewer: "RunViewer", client) -> None:
        self.viewer, self.client = viewer, client
        self.wake = threading.Event()
        self.moving = False
        self.stopped = False
        self.errors = 0
        gui = client.gui
        maps = viewer.renderer.maps
        self.map = gui.add_dropdown("Map", [_LABELS[m] for m in maps], initial_value=_LABELS[maps[0]])
        decomposed = viewer.renderer.decomposed
        self.exposure = gui.add_slider("Exposure", 0.2, 3.0, 0.05, 1.0, disabled=not decomposed,
                                       hint="< 1 brighter, > 1 darker (the light divided by it; with a gamma "
                                            "tone, the gamma times it)")
        self.use_gamma = gui.add_checkbox("Absolute gamma", False, disabled=not decomposed)
        lo, hi = gamma_slider_range(viewer.renderer.model if decomposed else None)
        self.gamma = gui.add_slider("Gamma", lo, hi, 0.01, round(0.5 * (lo + hi), 2), disabled=not decomposed)
        modes = list(WB_MODES)
        self.wb_mode = gui.add_dropdown("White balance", modes, initial_value=modes[0],
                                        hint="an edit of the enhanced light before the highlight shoulder, as "
                                             "render/export --white-balance")
        self.kelvin = gui.add_slider("Temperature (K)", TEMP_SLIDER[0], TEMP_SLIDER[1], 50.0, 6504.0,
                                     hint="the light the scene is taken to be lit by: 6504 = as trained, higher = "
                                          "warmer image")
        self.tint = gui.add_slider("Tint", -100.0, 100.0, 1.0, 0.0, hint="+ magenta, - green")
        self.gains = gui.add_vector3("Gains R,G,B", (1.0, 1.0, 1.0), min=(0.05, 0.05, 0.05), max=(20.0, 20.0, 20.0),
                                     step=0.01, hint="divided by G: brightness stays the exposure's")
        self.pick = gui.add_button("Pick a neutral (then click the view)",
                                   hint="the next click on the view makes that pixel grey (sets the gains)")
        self.wb_note = gui.add_text("White balance used", "as trained", disabled=True)
        self.shoulder = gui.add_checkbox("Highlight shoulder", True, disabled=not viewer.renderer.has_shoulder,
                                         hint="on: highlights roll off at the run's knee; off: clip at white")
        self.scale = gui.add_slider("Resolution scale", 0.1, 2.0, 0.05, viewer.default_scale)
        self.lowres = gui.add_checkbox("Lower resolution while moving", True)
        names = list(viewer.cameras)
        self.camera_pick = gui.add_dropdown("Camera", names or ["(none)"], disabled=not names)
        self.snap = gui.add_button("Snap to camera", disabled=not names)
        self.frame_time = gui.add_text("Frame time", "-", disabled=True)
        for handle in (self.map, self.exposure, self.use_gamma, self.gamma, self.scale, self.kelvin, self.tint,
                       self.gains, self.shoulder):
            handle.on_update(lambda _: self.request(moving=False))
        self.wb_mode.on_update(lambda _: self._mode_changed())
        self.pick.on_click(lambda _: self._arm_pick())
        self._picking = False
        self.snap.on_click(lambda _: self.snap_to(self.camera_pick.value))
        client.camera.on_update(lambda _: self.request(moving=True))
        self.thread = threading.Thread(target=self._loop, name=f"retinexgs-view-{client.client_id}", daemon=True)
        self.thread.start()
        # Start at the first training camera (viser's default camera knows nothing of the scene). viser calls
        # connect after the client's first camera message, possibly after that message's camera callbacks ran
        # (without ours): draw the first frame now either way.
        if names:
            self.snap_to(names[0])
        self.request(moving=False)

    def settings(self) -> FrameSettings:
        """The controls' values; a number typed into a slider's box is clamped to the slider's range (the
        browser sends the intermediate values of typing, e.g. 0 on the way to 0.3). NaN stays NaN and is
        refused by the renderer."""
        key = {v: k for k, v in _LABELS.items()}[self.map.value]

        def clamped(handle) -> float:
            return max(min(float(handle.value), handle.max), handle.min)

        gamma = clamped(self.gamma) if self.use_gamma.value else None
        return FrameSettings(map=key, exposure=clamped(self.exposure), gamma=gamma, scale=clamped(self.scale),
                             white_balance=self.white_balance_form(), shoulder=bool(self.shoulder.value))

    def white_balance_form(self) -> str:
        """The white-balance controls as a ``render --white-balance`` form; typed numbers are clamped to the
        controls' ranges as the sliders' are (NaN stays NaN: the renderer refuses it)."""
        mode = WB_MODES.get(self.wb_mode.value, "as-trained")

        def clamp(value: float, lo: float, hi: float) -> float:
            return max(min(float(value), hi), lo)

        if mode == "temp":
            return (f"temp:{clamp(self.kelvin.value, self.kelvin.min, self.kelvin.max)!r},"
                    f"{clamp(self.tint.value, self.tint.min, self.tint.max)!r}")
        if mode == "gains":
            lo, hi = self.gains.min or (0.05,) * 3, self.gains.max or (20.0,) * 3
            return "gains:" + ",".join(repr(clamp(v, a, b)) for v, a, b in zip(self.gains.value, lo, hi))
        return mode

    def _mode_changed(self) -> None:
        if WB_MODES.get(self.wb_mode.value) == "auto":
            self.viewer.renderer.forget_auto()  # measured anew each time it is chosen (a live scene moves on)
        self.request(moving=False)

    def _arm_pick(self) -> None:
        """The eyedropper: the next click on the canvas picks (viser's scene click gives its screen position)."""
        if self._picking:
            return
        self._picking = True
        self.wb_note.value = "click a neutral (grey or white) surface in the view"
        self.client.scene.on_click()(self._picked)

    def _picked(self, event) -> None:
        self.client.scene.remove_click_callback(self._picked)  # one click only: the camera drags again after it
        self._picking = False
        try:
            u, v = (float(t) for t in event.screen_pos)
            cam = self.client.camera
            vc = ViewerCamera(tuple(cam.wxyz), tuple(cam.position), float(cam.fov), int(cam.image_width),
                              int(cam.image_height))
            settings = replace(self.settings(), white_balance="as-trained")
            gains = self.viewer.renderer.pick_neutral(vc, settings, u, v)
        except UserError as exc:  # black or clipped: said in the panel, the balance stays as it was
            self.wb_note.value = str(exc)
            return
        except Exception as exc:  # junk from a client must not reach viser's threads
            self.wb_note.value = f"the pick failed: {type(exc).__name__}: {exc}"
            return
        with self.client.atomic():
            self.gains.value = tuple(float(g) for g in gains)
            self.wb_mode.value = next(k for k, m in WB_MODES.items() if m == "gains")
        self.request(moving=False)

    def request(self, moving: bool) -> None:
        self.moving = self.moving or moving
        self.wake.set()

    def snap_to(self, name: str) -> None:
        camera = self.viewer.cameras.get(name)
        if camera is None:
            return
        vc = camera_to_viewer(camera)
        with self.client.atomic():
            self.client.camera.position = vc.position
            self.client.camera.wxyz = vc.wxyz
            self.client.camera.fov = vc.fov
        self.request(moving=False)

    def _loop(self) -> None:
        pending_full = False
        while not (self.stopped or self.viewer.stopped):
            woke = self.wake.wait(SETTLE_SECONDS)
            if self.stopped or self.viewer.stopped:
                break
            if woke:
                self.wake.clear()
                low = self.moving and bool(self.lowres.value)
                self.moving = False
                self.draw(low)
                pending_full = low
            elif pending_full:
                pending_full = False
                self.draw(False)

    def draw(self, low: bool) -> None:
        """Render and send one frame; any failure is logged (the first few of each client) and skipped."""
        try:
            cam = self.client.camera
            vc = ViewerCamera(tuple(cam.wxyz), tuple(cam.position), float(cam.fov), int(cam.image_width),
                              int(cam.image_height))
            settings = self.settings()
            if low:
                settings = replace(settings, scale=settings.scale * MOVING_SCALE)
            start = time.perf_counter()
            frame = self.viewer.renderer.render(vc, settings)
            ms = 1000 * (time.perf_counter() - start)
            self.client.scene.set_background_image(frame, format="jpeg", jpeg_quality=90)
            self.frame_time.value = f"{ms:.0f} ms ({frame.shape[1]}x{frame.shape[0]}{', moving' if low else ''})"
            note = self.viewer.renderer.balance_text
            if not self._picking and settings.map == "enhanced" and self.wb_note.value != note:
                self.wb_note.value = note  # the numbers used, as render prints them
            self.viewer.frames += 1
            self.viewer.last_frame = frame
        except Exception as exc:  # a viewer must survive junk from a client and renderer errors
            self.errors += 1
            if self.errors <= 3:
                self.viewer.log(f"retinexgs view: frame for client {self.client.client_id} failed: "
                                f"{type(exc).__name__}: {exc}")


class RunViewer:
    """A viser server showing ``renderer``'s scene. ``cameras``: name -> camera for the snap list; ``up``: the
    world's up direction. ``port`` 0 picks a free port; :attr:`url` is where it serves."""

    def __init__(self, renderer: FrameRenderer, cameras: Dict[str, Camera], host: str = "127.0.0.1",
                 port: int = 8080, default_scale: float = 1.0, log: Callable[[str], None] = print) -> None:
        viser = import_viser()
        self.renderer, self.cameras, self.log = renderer, cameras, log
        self.default_scale = default_scale
        self.stopped = False
        self.frames = 0
        self.last_frame = None  # the newest frame sent to any client (for tests and diagnostics)
        self._clients: Dict[int, _Client] = {}
        check_bindable(host, port)  # viser retries a failed bind on the next port forever: it would hang
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.requested_port = port
        self.server.scene.set_up_direction(average_up(list(cameras.values())) if cameras else "+z")
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def port_note(self) -> str:
        """'' when serving on the port asked for (or any, for 0); else a note that it was taken."""
        got = self.server.get_port()
        if self.requested_port in (0, got):
            return ""
        return f" (port {self.requested_port} was taken, so {got} is used)"

    def _connect(self, client) -> None:
        try:
            self._clients[client.client_id] = _Client(self, client)
        except Exception as exc:
            self.log(f"retinexgs view: could not set up client {client.client_id}: {type(exc).__name__}: {exc}")

    def _disconnect(self, client) -> None:
        state = self._clients.pop(client.client_id, None)
        if state is not None:
            state.stopped = True
            state.wake.set()

    def stop(self) -> None:
        """Stop the server and every render thread (bounded: viser joins its threads with timeouts)."""
        self.stopped = True
        for state in list(self._clients.values()):
            state.stopped = True
            state.wake.set()
        self.server.stop()


def snap_cameras(scene) -> Dict[str, Camera]:
    """'train: NAME' / 'test: NAME' -> camera, for the snap list."""
    out: Dict[str, Camera] = {}
    for split in ("train", "test"):
        for v in getattr(scene, split):
            out[f"{split}: {v.name}"] = view_camera(v)
    return out


def check_address(host: str, port: int) -> None:
    """UserError for a port outside 0..65535, an empty host, or an address that cannot be bound
    (:func:`check_bindable`)."""
    if not isinstance(port, int) or not 0 <= port <= 65535:
        raise UserError(f"--port must be 0..65535 (0 picks a free port), got {port}")
    if not host:
        raise UserError("--host is empty; give an address to bind, e.g. 127.0.0.1")
    check_bindable(host, port)


def check_bindable(host: str, port: int) -> None:
    """UserError when ``host`` is not an address (or name) of this machine, or ``port`` may not be bound there
    (a port below 1024 without root). A port in use is fine: the server takes the next free one.

    viser's server thread swallows every bind error and tries the next port, a thousand times, for each
    address; the caller waits on it without a timeout, so such an address would hang ``view`` silently."""
    import errno
    import socket
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        raise UserError(f"--host {host!r} is not an IP address or a host name that resolves ({reason}); "
                        "e.g. 127.0.0.1 (this machine only) or 0.0.0.0 (every interface)") from None
    bound = False
    for family, kind, proto, _, address in infos:
        with socket.socket(family, kind, proto) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server binds
            if family == socket.AF_INET6 and hasattr(socket, "IPV6_V6ONLY"):
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                sock.bind(address)
                bound = True
            except PermissionError:
                raise UserError(f"--port {port}: no permission to bind {host}:{port} (ports below 1024 need "
                                "root); use a port from 1024 up, or 0 for any free port") from None
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:  # taken: the server moves on to the next free port
                    bound = True
                elif exc.errno != errno.EADDRNOTAVAIL:  # (one family of a name may be missing, as in asyncio)
                    raise UserError(f"cannot bind --host {host} --port {port}: {exc.strerror or exc}") from None
    if not bound:
        raise UserError(f"--host {host}: not an address of this machine, cannot bind it (use 127.0.0.1 for "
                        "this machine only or 0.0.0.0 for every interface)")


def view_run(run_dir, host: str = "127.0.0.1", port: int = 8080, device: Optional[str] = None,
             log: Callable[[str], None] = print, block: bool = True) -> RunViewer:
    """Serve ``run_dir`` in the browser; with ``block``, until Ctrl-C. The address, then the run, then the
    viser install are checked, each with a UserError."""
    check_address(host, port)
    cfg, scene, model, step = load_run(run_dir, device)
    import_viser()
    renderer = FrameRenderer(model, cfg, active_sh_degree(cfg, step), scene.train)
    on_gpu = model.gaussians.means.is_cuda
    viewer = RunViewer(renderer, snap_cameras(scene), host, port, default_scale=1.0 if on_gpu else 0.5, log=log)
    if not block:
        _announce(viewer, run_dir, step, len(model.gaussians), host, log)
        return viewer
    try:  # from the URL line on: a Ctrl-C right after it (a user, a test) is a clean stop, not a traceback
        _announce(viewer, run_dir, step, len(model.gaussians), host, log)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt as exc:
        log("retinexgs view: stopping")
        if isinstance(exc, Terminated):  # SIGTERM: the CLI says "terminated" and exits with 143
            raise
    finally:
        viewer.stop()
    return viewer


def gamma_slider_range(model) -> Tuple[float, float]:
    """The absolute-gamma slider's (min, max): the range the run's EnhancementNet predicts in (its tone's own:
    0.1-1 for a gamma curve, 0.25-2 for the exposure tone), widened a little; a fixed range for baselines."""
    if model is None:
        return 0.05, 1.5
    net = model.enhancement
    return round(0.5 * net.g_min, 2), round(1.25 * net.g_max, 2)


def _announce(viewer: RunViewer, run_dir, step: int, count: int, host: str, log: Callable[[str], None]) -> None:
    log(f"retinexgs view: {run_dir} (step {step}, {count} Gaussians) at {viewer.url}{viewer.port_note()}")
    if host not in ("127.0.0.1", "localhost", "::1"):
        log(f"retinexgs view: bound to {host}: anyone who can reach this machine on port "
            f"{viewer.server.get_port()} can see the scene")

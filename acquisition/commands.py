"""CLI command functions of the acquisition package (registered by gearscan/cli.py).

Only light imports at module level; drivers are imported inside the functions.
"""

from __future__ import annotations

import typer


def devices(
    timeout: float = typer.Option(1.0, help="Seconds to listen on each serial port for an encoder."),
    port: list[str] = typer.Option([], help="Also probe this serial port or link (e.g. the mock encoder's pty); repeat."),
    probe: bool = typer.Option(True, help="Send HELLO (the encoder protocol's only command) to each serial port and listen."),
) -> None:
    """List cameras with their features (Aravis: GigE/USB3 Vision; V4L2) and what answers on each serial port."""
    from rich.console import Console
    from rich.table import Table

    from gearscan.acquisition.camera import CameraError
    from gearscan.acquisition.encoder import list_serial_ports
    from gearscan.acquisition.probe import probe_encoder
    from gearscan.acquisition.v4l2 import list_v4l2_devices

    console = Console()
    table = Table(title="Cameras")
    for col in ("driver", "id", "vendor", "model", "serial", "address"):
        table.add_column(col)
    notes, features = [], []
    try:
        from gearscan.acquisition.aravis import AravisCamera, list_cameras

        for c in list_cameras():
            table.add_row(c.driver, c.id, c.vendor, c.model, c.serial, c.address)
            try:
                with AravisCamera(c.id) as cam:
                    features.append((c.id, cam.features()))
            except CameraError as exc:
                notes.append(f"{c.id}: cannot open to read its features ({exc})")
    except CameraError as exc:
        notes.append(f"Aravis: {exc}")
    for c in list_v4l2_devices():
        table.add_row(c.driver, c.id, c.vendor, c.model, c.serial, c.address)
    console.print(table if table.row_count else "No camera found. Is one connected and powered? (GigE: same subnet?)")
    for cam_id, feats in features:
        ft = Table(title=f"{cam_id}: features (camera.* in the live config)")
        ft.add_column("feature")
        ft.add_column("offered")
        for k, v in feats.items():
            ft.add_row(k, v)
        console.print(ft)
    for n in notes:
        console.print(f"[yellow]{n}[/yellow]")
    ports = list(dict.fromkeys([*list_serial_ports(), *port]))
    if not ports:
        console.print("Serial ports: none found (encoder unplugged? a pty or link: --port PATH)")
        return
    st = Table(title="Serial ports (encoder.port)")
    st.add_column("port")
    st.add_column("answer" if probe else "not probed (--no-probe)")
    for p in ports:
        st.add_row(p, probe_encoder(p, timeout_s=timeout).describe() if probe else "")
    console.print(st)

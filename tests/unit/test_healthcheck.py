"""The container health check reads the kernel's TCP tables: parsing and verdicts on made-up tables."""

import pytest

from services.healthcheck import check, endpoint_ports, sockets

HEADER = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode\n"


def table(tmp_path, *rows: tuple[str, str, str]):
    path = tmp_path / "tcp"
    path.write_text(HEADER + "".join(f"   {i}: {local} {remote} {state} 00000000:00000000 00:00000000 00000000 0 0 1\n"
                                     for i, (local, remote, state) in enumerate(rows)))
    return (path, tmp_path / "absent-tcp6")


def test_endpoint_ports_of_every_zenoh_locator_form():
    assert endpoint_ports("tcp/router:7447") == {7447}
    assert endpoint_ports("tls/[::1]:7448?so_sndbuf=1#iface=eth0, tcp/10.0.0.1:1") == {7448, 1}
    assert endpoint_ports("") == set()


def test_sockets_parse_hex_ports_and_states(tmp_path):
    assert sockets(table(tmp_path, ("0100007F:1D17", "00000000:0000", "0A"))) == [(7447, 0, "0A")]


@pytest.mark.parametrize("rows, healthy", [
    ([("00000000:1D17", "00000000:0000", "0A")], True),     # listening on 7447
    ([("00000000:1D18", "00000000:0000", "0A")], False),    # listening elsewhere
    ([("0A00000A:9C40", "0100000A:1D17", "01")], False),    # only a client connection
])
def test_router_is_healthy_when_it_listens_on_its_port(tmp_path, monkeypatch, rows, healthy):
    monkeypatch.setenv("FLEETSLAM_LISTEN", "tcp/0.0.0.0:7447")
    assert (check("router", table(tmp_path, *rows)) is None) is healthy


@pytest.mark.parametrize("rows, healthy", [
    ([("0A00000A:9C40", "0100000A:1D17", "01")], True),     # established to the router's port
    ([("0A00000A:9C40", "0100000A:1D17", "02")], False),    # still connecting (SYN_SENT)
    ([("0A00000A:9C40", "0100000A:0050", "01")], False),    # established, but elsewhere
    ([], False),
])
def test_client_is_healthy_only_while_connected_to_the_router(tmp_path, monkeypatch, rows, healthy):
    monkeypatch.setenv("FLEETSLAM_ZENOH_CONNECT", "tcp/router:7447")
    problem = check("client", table(tmp_path, *rows))
    assert (problem is None) is healthy
    if not healthy:
        assert "7447" in problem

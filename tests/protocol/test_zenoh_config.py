"""``tidee.protocol.zenoh_config``: tidee's Zenoh settings, an operator's config file merged over
them key by key, and one-line errors naming a bad file. Fast: no session is opened except where a
refusal is the point."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from tests.support import REPO
from tidee.launch import free_port
from tidee.protocol import zenoh_config as zc
from tidee.protocol.zenoh_config import (
    CONFIG_ENV,
    ZenohConfigError,
    ZenohOpenError,
    make_config,
    merged_config,
    open_session,
    router_defaults,
)

PEM = "-----BEGIN CERTIFICATE-----\nnot checked here\n-----END CERTIFICATE-----\n"
ROUTER = "tcp/127.0.0.1:7999"


@pytest.fixture(autouse=True)
def _no_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for env in (CONFIG_ENV, zc.ENDPOINT_ENV, zc.ROUTER_ENV):
        monkeypatch.delenv(env, raising=False)


def _get(conf: zenoh.Config, key: str) -> object:
    return json.loads(conf.get_json(key))


def _file(tmp_path: Path, text: str, name: str = "z.json5") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_without_a_file_tidee_s_defaults_hold() -> None:
    conf = make_config(False, endpoint="tcp/127.0.0.1:7001")
    assert _get(conf, "mode") == "peer"
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7001"]
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:0"]
    assert _get(conf, "scouting/multicast/enabled") is False
    client = make_config(False, router=ROUTER)
    assert (_get(client, "mode"), _get(client, "connect/endpoints")) == ("client", [ROUTER])


def test_the_file_wins_key_by_key_and_tidee_fills_the_rest(tmp_path: Path) -> None:
    path = _file(
        tmp_path,
        """{
          // a comment, a trailing comma: JSON5
          scouting: { gossip: { enabled: false }, },
          connect: { endpoints: ["tcp/127.0.0.1:7002"] },
          transport: { link: { tx: { lease: 3000 } } },
        }""",
    )
    conf = make_config(False, endpoint="tcp/127.0.0.1:7001", zenoh_config=path)
    assert _get(conf, "scouting/gossip/enabled") is False  # the file's
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7002"]  # the file's, the whole list
    assert _get(conf, "transport/link/tx/lease") == 3000  # the file's, a key tidee never sets
    assert _get(conf, "scouting/delay") == 0  # tidee's, beside the file's scouting keys
    assert _get(conf, "scouting/multicast/enabled") is False  # tidee's
    assert _get(conf, "mode") == "peer"  # tidee's
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:0"]  # tidee's


def test_the_file_s_mode_and_scouting_win_over_tidee_s(tmp_path: Path) -> None:
    path = _file(tmp_path, '{ mode: "client", scouting: { multicast: { enabled: true } } }')
    conf = make_config(False, router=ROUTER, zenoh_config=path)
    assert _get(conf, "mode") == "client"
    assert _get(conf, "scouting/multicast/enabled") is True  # the file overrides tidee's false
    assert _get(conf, "connect/endpoints") == [ROUTER]  # --router, since the file names none


def test_the_environment_variable_gives_the_file_and_the_argument_beats_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from_env = _file(tmp_path, "{ transport: { link: { tx: { lease: 4000 } } } }", "env.json5")
    given = _file(tmp_path, "{ transport: { link: { tx: { lease: 5000 } } } }", "given.json5")
    monkeypatch.setenv(CONFIG_ENV, from_env)
    assert _get(make_config(False), "transport/link/tx/lease") == 4000
    assert _get(make_config(False, zenoh_config=given), "transport/link/tx/lease") == 5000


def test_relative_certificate_paths_are_relative_to_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "deploy" / "certs").mkdir(parents=True)
    (tmp_path / "deploy" / "certs" / "ca.pem").write_text(PEM)
    (tmp_path / "abs.pem").write_text(PEM)
    path = _file(
        tmp_path / "deploy",
        f'{{ transport: {{ link: {{ tls: {{ root_ca_certificate: "certs/ca.pem", '
        f'connect_certificate: "{tmp_path / "abs.pem"}" }} }} }} }}',
    )
    monkeypatch.chdir(REPO)  # elsewhere
    conf = make_config(False, router=ROUTER, zenoh_config=path)
    assert _get(conf, "transport/link/tls/root_ca_certificate") == str(
        tmp_path / "deploy" / "certs" / "ca.pem"
    )
    assert _get(conf, "transport/link/tls/connect_certificate") == str(tmp_path / "abs.pem")


def test_the_router_s_defaults_and_its_file(tmp_path: Path) -> None:
    path = _file(tmp_path, '{ listen: { endpoints: ["tcp/127.0.0.1:7003"] } }')
    conf = merged_config(router_defaults(["tcp/127.0.0.1:7004"]), path)
    assert _get(conf, "mode") == "router"
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7003"]  # the file's over --listen
    assert _get(conf, "connect/endpoints") == []


BAD_FILES = [
    (None, "no such file"),
    ('{ mode: "client" scouting: }', "Zenoh cannot read it: line 1, column"),
    ("{ nosuchkey: 1 }", "unknown field `nosuchkey`"),
    ('{ mode: "banana" }', "unknown variant `banana`"),
    ('{ access_control: { enabled: true, rules: [{ id: "r" }] } }', "missing field"),
    ('{ transport: { link: { tls: { root_ca_certificate: "nowhere/ca.pem" } } } }', "no such file"),
    ('{ transport: { link: { tls: { listen_certificate: "z.json5" } } } }', "is not a PEM file"),
]


@pytest.mark.parametrize("text,expected", BAD_FILES, ids=[e for _, e in BAD_FILES])
def test_a_bad_file_is_one_line_naming_it_and_the_problem(
    tmp_path: Path, text: str | None, expected: str
) -> None:
    path = str(tmp_path / "z.json5") if text is None else _file(tmp_path, text)
    with pytest.raises(ZenohConfigError) as info:
        make_config(False, router=ROUTER, zenoh_config=path)
    message = str(info.value)
    assert message.startswith(f"--zenoh-config {path}: ") and expected in message, message
    assert "\n" not in message and ".rs:" not in message, message


def test_a_file_without_a_known_extension_is_refused(tmp_path: Path) -> None:
    path = _file(tmp_path, '{ mode: "client" }', "zenoh.conf")
    with pytest.raises(ZenohConfigError, match=r"\.json, \.json5 and \.yaml"):
        make_config(False, zenoh_config=path)


def test_a_bad_file_from_the_environment_names_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(CONFIG_ENV, "/nonexistent/z.json5")
    with pytest.raises(ZenohConfigError, match=f"^{CONFIG_ENV}=/nonexistent/z.json5: no such file$"):
        make_config(False)


def test_a_refused_connection_names_the_router_and_the_file(tmp_path: Path) -> None:
    path = _file(tmp_path, "{ transport: { link: { tx: { lease: 3000 } } } }")
    router = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    with pytest.raises(ZenohOpenError) as info:
        open_session(False, router=router, zenoh_config=path)
    assert str(info.value).startswith(
        f"--router {router} with --zenoh-config {path}: Zenoh could not connect"
    )


@pytest.mark.parametrize("role", ["router", "server", "agent", "viewer", "evaluator"])
def test_the_shipped_secure_files_are_valid_zenoh_configs(role: str) -> None:
    conf = zenoh.Config.from_file(str(REPO / "deploy" / "secure" / f"{role}.json5"))
    assert _get(conf, "transport/link/protocols") == ["tls"]
    assert _get(conf, "transport/link/tls/enable_mtls") is True
    if role != "router":
        assert _get(conf, "mode") == "client"  # through the router only
        assert _get(conf, "transport/link/tls/connect_certificate") == f"certs/{role}.pem"
        return
    acl = _get(conf, "access_control")
    assert isinstance(acl, dict) and acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"] for r in acl["rules"]}
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects == {name: [name] for name in ("server", "agent", "evaluator", "viewer")}
    used = {r for p in acl["policies"] for r in p["rules"]}
    assert used == rules, "every rule is in a policy, every policy's rule exists"
    assert all(r["permission"] == "allow" for r in acl["rules"]), "default deny: rules only allow"
    state = {
        p["id"]
        for p in acl["policies"]
        for r in acl["rules"]
        if r["id"] in p["rules"] and any(k.endswith("/state") for k in r["key_exprs"])
    }
    assert state == {"evaluator"}, "only the evaluator's policy names the state key"

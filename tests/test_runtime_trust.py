"""`fbgcomp trust add|list` (the OPC UA trust list) and the ReloadModel folder rule, without a
server (tests/test_runtime_opcua.py has them against the real server and a real client)."""

import datetime as dt
import os
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fbgcomp_testing import cli

pytest.importorskip("cryptography")


def _certificate(days=365, uri="urn:test:plc", cn="plc-7"):
    """(certificate, DER bytes, PEM bytes) of a fresh self-signed client certificate."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])
    now = dt.datetime.now(dt.UTC)
    start = now - dt.timedelta(days=2 * abs(days)) if days < 0 else now - dt.timedelta(minutes=5)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.SubjectAlternativeName([x509.UniformResourceIdentifier(uri)]), critical=False)
        .sign(key, hashes.SHA256())
    )
    return (
        cert,
        cert.public_bytes(serialization.Encoding.DER),
        cert.public_bytes(serialization.Encoding.PEM),
    )


def _fbgcomp(*args):
    p = cli(*args)
    return p.returncode, p.stdout, p.stderr


def _one_line_error(code, err, fragment):
    assert code == 2, err
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and fragment in err, err


def test_trust_add_takes_pem_or_der_writes_der_and_is_idempotent(tmp_path):
    _, der, pem = _certificate()
    (tmp_path / "plc.pem").write_bytes(pem)
    (tmp_path / "plc.der").write_bytes(der)
    trusted = tmp_path / "state" / "opcua" / "trusted"
    code, out, err = _fbgcomp("trust", "add", tmp_path / "plc.pem", "--state-dir", tmp_path / "state")
    assert code == 0, err
    assert out.startswith("trusted: ") and "CN=plc-7" in out and "urn:test:plc" in out
    files = sorted(trusted.iterdir())
    assert len(files) == 1 and files[0].suffix == ".der" and files[0].read_bytes() == der
    code, out, _ = _fbgcomp("trust", "add", tmp_path / "plc.der", "--dir", trusted)
    assert code == 0 and out.startswith("already trusted: ")
    assert sorted(trusted.iterdir()) == files  # nothing written, no temporary left
    code, out, _ = _fbgcomp("trust", "list", "--dir", trusted)
    assert code == 0 and "(1 certificate(s))" in out and "CN=plc-7" in out


@pytest.mark.parametrize(
    "content, fragment",
    [
        (b"-----BEGIN CERTIFICATE-----\nnot base64\n-----END CERTIFICATE-----\n", "not an X.509"),
        (b"\x30\x82\x01\x00" + os.urandom(300), "not an X.509"),
        (b"", "not an X.509"),
        (b"x" * (65 * 1024), "not a certificate"),
        ("two", "holds 2 certificates"),
        ("expired", "expired on"),
        ("key-only", "holds 0 certificates"),
    ],
    ids=["bad-pem", "bad-der", "empty", "huge", "two-certs", "expired", "key-only"],
)
def test_trust_add_refuses_what_is_not_one_valid_certificate(tmp_path, content, fragment):
    if content == "two":
        content = _certificate()[2] + _certificate(cn="other")[2]
    elif content == "expired":
        content = _certificate(days=-1)[1]
    elif content == "key-only":
        content = b"-----BEGIN PRIVATE KEY-----\nAAAA\n-----END PRIVATE KEY-----\n"
    cert = tmp_path / "client.der"
    cert.write_bytes(content)
    trusted = tmp_path / "trusted"
    code, _out, err = _fbgcomp("trust", "add", cert, "--dir", trusted)
    _one_line_error(code, err, fragment)
    assert "client.der" in err  # the file is named
    assert not trusted.exists() or not any(trusted.iterdir())


def test_trust_add_errors_name_the_file_or_folder(tmp_path):
    code, _, err = _fbgcomp("trust", "add", tmp_path / "nope.der", "--dir", tmp_path / "t")
    _one_line_error(code, err, "nope.der: certificate file not found")
    (tmp_path / "plc.der").write_bytes(_certificate()[1])
    (tmp_path / "afile").write_text("")
    code, _, err = _fbgcomp("trust", "add", tmp_path / "plc.der", "--dir", tmp_path / "afile")
    _one_line_error(code, err, "afile: trust list is not a folder")


def test_serve_refuses_a_missing_models_folder(tmp_path):
    code, _, err = _fbgcomp(
        "serve",
        "--model",
        "m.json",
        "--source",
        "replay://x",
        "--models-dir",
        tmp_path / "no-such-folder",
        "--opcua",
        "off",
    )
    _one_line_error(code, err, "no-such-folder")


@pytest.fixture(scope="session")
def models(tmp_path_factory):
    base = tmp_path_factory.mktemp("reload")
    folder = base / "models"
    (folder / "sub").mkdir(parents=True)
    for name in ("a.json", "sub/b.json"):
        (folder / name).write_text("{}")
    (base / "outside.json").write_text("{}")
    (folder / "out.json").symlink_to(base / "outside.json")
    (folder / "sub" / "up").symlink_to(base)
    (folder / "inner.json").symlink_to(folder / "a.json")
    return folder


_piece = st.sampled_from(
    [
        "a.json",
        "sub",
        "b.json",
        "..",
        ".",
        "out.json",
        "up",
        "outside.json",
        "inner.json",
        "",
        "/",
        "etc",
        "passwd",
        "~",
    ]
)


@settings(max_examples=300, deadline=None)
@given(parts=st.lists(_piece, max_size=6), lead=st.sampled_from(["", "/", "./"]))
def test_reload_model_names_never_leave_the_models_folder(models, parts, lead):
    """Whatever name a client sends, ReloadModel either refuses it or loads an existing file
    inside the folder (symbolic links resolved)."""
    from fbgcomp.runtime.outputs.opcua import ModelPathRefused, model_in_folder

    name = lead + "/".join(parts)
    try:
        path = model_in_folder(name, models)
    except ModelPathRefused as exc:
        assert exc.status in ("BadInvalidArgument", "BadNotFound")
        return
    if not name:
        assert path == ""
        return
    assert Path(path).is_file()
    assert Path(path).resolve().is_relative_to(models.resolve())
    assert not Path(name).is_absolute() and ".." not in Path(name).parts

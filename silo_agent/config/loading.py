"""Reading a TOML file into a `Config`: strict parsing, one line per problem naming the key,
and the environment checks `run` and `check-config` make."""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path

from pydantic import (
    ValidationError,
)

from silo_agent.base.files import FileProblem, read_regular, writable_directory_problem
from silo_agent.base.limits import MAX_CONFIG_BYTES
from silo_agent.config.base import ConfigError, describe_validation_error
from silo_agent.config.mqtt import MqttTlsConfig, read_secret
from silo_agent.config.root import Config
from silo_agent.config.web import token_problem


def _toml_value(value: object) -> object:
    """A TOML date or time in the JSON handed to the strict validator: an object, which no
    key of the config accepts, so the error names the key."""
    return {"toml date/time": str(value)}


def parse_config(data: dict, source: str) -> Config:
    """Validate a parsed TOML document, strictly (no `true` or `"30"` for a number); `source`
    names it in errors. Validated as JSON, where strict mode still takes a string for a path
    and an array for a tuple, as TOML writes them."""
    try:
        document = json.dumps(data, default=_toml_value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{source}: {exc}") from None
    try:
        return Config.model_validate_json(document, strict=True)
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, source)) from None


def _outbox_problem(outbox: Path) -> str | None:
    """Why the agent could not keep its outbox at `outbox`, or None."""
    problem = writable_directory_problem(outbox.parent)
    if problem:
        return problem
    try:
        if outbox.exists() and not outbox.is_file():
            return f"{outbox} exists and is not a regular file"
    except OSError as exc:
        return f"cannot use {outbox}: {exc.strerror or exc}"
    return None


def _readable_file_problem(path: Path) -> str | None:
    try:
        if not path.exists():
            return f"{path} does not exist"
        if not path.is_file():  # checked before opening: a FIFO would block the open
            return f"{path} is not a regular file"
        with open(path, "rb"):
            pass
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    return None


def _input_problems(config: Config) -> list[str]:
    """`key: problem` for the files every command reads as the config says: the ONNX model,
    which `run` and `scan` would otherwise fail on only after capturing. A relative path is
    taken from the working directory, as the model is then opened."""
    onnx = config.detection.onnx
    problem = None if onnx is None else _readable_file_problem(onnx.model)
    if onnx is None or problem is None:
        return []
    if not onnx.model.is_absolute():
        problem += f" (a relative path is taken from the working directory, {Path.cwd()})"
    return [f"detection.onnx.model: {problem}"]


def _tls_problems(tls: MqttTlsConfig) -> list[str]:
    """`key: problem` for TLS files that exist but that the broker connection's SSL context
    would refuse: loaded into one the way paho's `tls_set` loads them, so that a bad file is a
    config error naming its key, not an SSL traceback on every reconnect."""
    import ssl

    problems: list[str] = []
    for key, path in (("ca_file", tls.ca_file), ("cert_file", tls.cert_file)):
        if path is None:
            continue
        try:  # any PEM certificate loads as a trust anchor, a client's too
            ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_verify_locations(cafile=path)
        except ssl.SSLError:
            problems.append(f"mqtt.tls.{key}: {path} holds no PEM certificate")
    if problems or tls.cert_file is None or tls.key_file is None:
        return problems
    if tls.key_password_file is None and tls.key_password_env is not None:
        if tls.key_password_env not in os.environ:  # the service's environment: checked at start
            return []
        hint = f"or the passphrase in ${tls.key_password_env} does not decrypt it"
    elif tls.key_password_file is not None:
        hint = "or the passphrase in key_password_file does not decrypt it"
    else:  # an encrypted key then fails here, rather than OpenSSL asking on a tty
        hint = "or it is encrypted and neither key_password_file nor key_password_env is given"
    try:  # as the agent reads it
        password = read_secret(tls.key_password_file, tls.key_password_env, "mqtt.tls.key_password")
    except ConfigError as exc:
        return [str(exc)]
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_cert_chain(
            tls.cert_file, tls.key_file, password or ""
        )
    except ssl.SSLError as exc:
        if exc.reason == "KEY_VALUES_MISMATCH":
            problem = f"{tls.key_file} is not the private key of cert_file {tls.cert_file}"
        else:
            problem = f"{tls.key_file} is not a PEM private key, {hint}"
        problems.append(f"mqtt.tls.key_file: {problem}")
    return problems


def environment_problems(config: Config) -> list[str]:
    """`key: problem` for what the config points at and the agent could not use: directories
    it writes, files it reads. Checked at start and by check-config, not on every parse."""
    problems = []
    for key, problem in (
        ("audit.directory", writable_directory_problem(config.audit.directory)),
        ("mqtt.outbox_path", _outbox_problem(config.mqtt.outbox_path)),
    ):
        if problem:
            problems.append(f"{key}: {problem}")
    files = {"mqtt.password_file": config.mqtt.password_file}
    if config.mqtt.tls is not None:
        tls = config.mqtt.tls
        files.update(
            {
                "mqtt.tls.ca_file": tls.ca_file,
                "mqtt.tls.cert_file": tls.cert_file,
                "mqtt.tls.key_file": tls.key_file,
                "mqtt.tls.key_password_file": tls.key_password_file,
            }
        )
    if config.web.enabled:
        files["web.token_file"] = config.web.token_file
    for key, path in files.items():
        problem = _readable_file_problem(path) if path is not None else None
        if problem:
            problems.append(f"{key}: {problem}")
    if config.mqtt.tls is not None and not problems:
        problems += _tls_problems(config.mqtt.tls)
    if config.web.enabled and config.web.token_file is not None and not problems:
        problem = token_problem(config.web.token_file)
        if problem:
            problems.append(f"web.token_file: {problem}")
    return problems


def config_warnings(config: Config) -> list[str]:
    """Settings that are valid but probably not meant: a cron line that never fires."""
    warnings = []
    if config.schedule.cron is not None:
        from datetime import UTC, datetime

        from apscheduler.triggers.cron import CronTrigger

        trigger = CronTrigger.from_crontab(config.schedule.cron, timezone=config.silo.timezone)
        if trigger.get_next_fire_time(None, datetime.now(UTC)) is None:
            warnings.append(
                f"schedule.cron: {config.schedule.cron!r} never fires "
                "(no such date); only scan_at_start, interval_s and requests scan"
            )
    return warnings


def load_config(path: str | Path, *, service: bool = False) -> Config:
    """Read and validate a TOML config file and the files every command reads as it says
    (`_input_problems`). `service`: also what the daemon will write and read
    (`environment_problems`), for `run`, its reloads and `check-config`; offline commands
    such as `process --config` need none of it."""
    path = Path(path)
    try:  # only a regular file: a FIFO blocked, /dev/zero was read for ever
        raw = read_regular(path, MAX_CONFIG_BYTES)
    except FileProblem as exc:
        raise ConfigError(f"{path}: {exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset "
            f"{exc.start} ({exc.reason})"
        ) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    config = parse_config(data, str(path))
    problems = _input_problems(config) + (environment_problems(config) if service else [])
    if service and config.mqtt.outbox_path.resolve() == path.resolve():
        # a corrupt outbox is moved aside and the agent starts afresh: this would move the config
        problems.append("mqtt.outbox_path: names this config file itself")
    if problems:
        raise ConfigError("\n".join(f"{path}: {problem}" for problem in problems))
    return config

"""Generates the reference pages of the docs site at build time (mkdocs-gen-files runs this file).

Nothing here is copied by hand: the HTTP API comes from ``openapi.json`` (what ``make openapi`` writes
from the app), the CLI from the argparse parsers ``edgepos`` runs, and the configuration table from the
settings model the service reads its environment with. A page that drifts from the code cannot exist.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import mkdocs_gen_files
from edgepos.api.settings import Settings
from edgepos.cli import COMMANDS, build_parser
from edgepos.pipelines.registry import PIPELINES

ROOT = Path(__file__).resolve().parents[2]
METHODS = ("get", "post", "put", "patch", "delete")


def _cell(text: object) -> str:
    """Text safe inside one Markdown table cell."""
    return str(text).replace("|", "\\|").replace("\n", " ").strip()


def _schema_name(schema: dict[str, Any]) -> str:
    """A short type name for a JSON schema: the component it refers to, or its type."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[`{name}`](#schema-{name.lower()})"
    for combiner in ("anyOf", "oneOf", "allOf"):
        if combiner in schema:
            return " or ".join(_schema_name(part) for part in schema[combiner])
    kind = schema.get("type", "object")
    if kind == "array":
        return f"array of {_schema_name(schema.get('items', {}))}"
    if "enum" in schema:
        return " \\| ".join(f"`{value}`" for value in schema["enum"])
    if "const" in schema:
        return f"`{schema['const']}`"
    return f"`{kind}`"


def _bounds(schema: dict[str, Any]) -> str:
    """The constraints a schema states (bounds, lengths, patterns), as they are validated."""
    parts = []
    for key, label in (
        ("minimum", "≥"),
        ("exclusiveMinimum", ">"),
        ("maximum", "≤"),
        ("exclusiveMaximum", "<"),
        ("minLength", "length ≥"),
        ("maxLength", "length ≤"),
        ("minItems", "items ≥"),
        ("maxItems", "items ≤"),
    ):
        if key in schema:
            parts.append(f"{label} {schema[key]}")
    if "pattern" in schema:
        parts.append(f"pattern `{schema['pattern']}`")
    if "default" in schema:
        parts.append(f"default `{json.dumps(schema['default'])}`")
    for combiner in ("anyOf", "oneOf"):
        for part in schema.get(combiner, []):
            inner = _bounds({k: v for k, v in part.items() if k != "default"})
            if inner:
                parts.append(inner)
    return ", ".join(parts)


def http_api(document: dict[str, Any]) -> str:
    """The HTTP API page: every operation with its parameters, body, answers, then every schema."""
    lines = [
        "# HTTP API",
        "",
        (
            f"Generated from `openapi.json` (OpenAPI {document.get('openapi', '')}, API version "
            f"{document['info'].get('version', '')}) when the site is built. The running service serves the "
            "same document at `/openapi.json`, and an interactive page at `/docs`."
        ),
        "",
    ]
    by_tag: dict[str, list[tuple[str, str, dict[str, Any]]]] = {}
    for path, item in document["paths"].items():
        for method in METHODS:
            if method in item:
                operation = item[method]
                tag = (operation.get("tags") or ["other"])[0]
                by_tag.setdefault(tag, []).append((method, path, operation))
    for tag, operations in by_tag.items():
        lines += [f"## {tag}", ""]
        for method, path, operation in operations:
            lines += [f"### `{method.upper()} {path}`", ""]
            if operation.get("summary"):
                lines += [f"**{operation['summary']}**", ""]
            if operation.get("description"):
                lines += [operation["description"].strip(), ""]
            parameters = operation.get("parameters", [])
            if parameters:
                lines += ["| parameter | in | type | required | description |", "|---|---|---|---|---|"]
                for parameter in parameters:
                    schema = parameter.get("schema", {})
                    described = " ".join(filter(None, [parameter.get("description", ""), _bounds(schema)]))
                    lines.append(
                        f"| `{parameter['name']}` | {parameter['in']} | {_schema_name(schema)} | "
                        f"{'yes' if parameter.get('required') else 'no'} | {_cell(described)} |"
                    )
                lines.append("")
            body = operation.get("requestBody")
            if body:
                for media, content in body.get("content", {}).items():
                    lines += [f"Request body (`{media}`): {_schema_name(content.get('schema', {}))}", ""]
            lines += ["| status | answer |", "|---|---|"]
            for status, response in operation.get("responses", {}).items():
                schemas = [
                    f"{_schema_name(content['schema'])} (`{media}`)"
                    for media, content in response.get("content", {}).items()
                    if "schema" in content
                ]
                lines.append(f"| {status} | {_cell(' '.join([response.get('description', ''), *schemas]))} |")
            lines.append("")
    lines += ["## Schemas", ""]
    for name, schema in sorted(document.get("components", {}).get("schemas", {}).items()):
        lines += [f"### {name} {{#schema-{name.lower()}}}", ""]
        if schema.get("description"):
            lines += [schema["description"].strip(), ""]
        properties = schema.get("properties", {})
        if properties:
            required = set(schema.get("required", []))
            lines += ["| field | type | required | description |", "|---|---|---|---|"]
            for field, field_schema in properties.items():
                described = " ".join(
                    filter(None, [field_schema.get("description", ""), _bounds(field_schema)])
                )
                lines.append(
                    f"| `{field}` | {_schema_name(field_schema)} | {'yes' if field in required else 'no'} | "
                    f"{_cell(described)} |"
                )
            lines.append("")
        elif "enum" in schema:
            lines += [f"One of {_schema_name(schema)}.", ""]
    return "\n".join(lines) + "\n"


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser]]:
    """The parsers of a parser's subcommands, in the order they were added."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found.extend(action.choices.items())
    return found


def _command_sections(name: str, parser: argparse.ArgumentParser, depth: int) -> list[str]:
    lines = [f"{'#' * depth} `{name}`", "", "```text", parser.format_help().rstrip(), "```", ""]
    for sub_name, sub_parser in _subcommands(parser):
        lines += _command_sections(f"{name} {sub_name}", sub_parser, min(depth + 1, 6))
    return lines


def cli() -> str:
    """The CLI page: the help of ``edgepos`` and of every subcommand, as argparse prints it (each
    subcommand's options are only configured when it is the one run, so each is built on its own)."""
    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal: the same page on every machine
    top = build_parser()
    lines = [
        "# Command line",
        "",
        (
            "Generated from the argparse parsers of `edgepos` when the site is built: each section is what "
            "`edgepos ... --help` prints."
        ),
        "",
        "## `edgepos`",
        "",
        "```text",
        top.format_help().rstrip(),
        "```",
        "",
    ]
    for name in COMMANDS:
        configured = dict(_subcommands(build_parser(name)))[name]
        lines += _command_sections(f"edgepos {name}", configured, 3)
    return "\n".join(lines) + "\n"


def configuration() -> str:
    """The configuration page: every ``EDGEPOS_*`` variable from the settings model."""
    prefix = Settings.model_config.get("env_prefix", "")
    lines = [
        "# Configuration",
        "",
        (
            "The service reads its configuration from environment variables (a `.env` file is not read). "
            "Generated from the settings model (`edgepos.api.settings.Settings`) when the site is built; an "
            "invalid value stops the service at start with a message naming the variable."
        ),
        "",
        "| variable | default | constraints | description |",
        "|---|---|---|---|",
    ]
    for name, field in Settings.model_fields.items():
        schema = Settings.model_json_schema()["properties"].get(name, {})
        default = field.get_default(call_default_factory=True)
        constraint = _bounds({k: v for k, v in schema.items() if k != "default"})
        if "enum" in schema:
            constraint = " ".join(filter(None, [constraint, "one of " + ", ".join(map(str, schema["enum"]))]))
        lines.append(
            f"| `{(prefix + name).upper()}` | `{json.dumps(default, default=str)}` | {_cell(constraint)} | "
            f"{_cell(field.description or '')} |"
        )
    return "\n".join(lines) + "\n"


def client_guide() -> str:
    """The Python client guide: the client package's README under the site's title for it."""
    text = (ROOT / "client" / "README.md").read_text(encoding="utf-8")
    body = text.split("\n", 1)[1] if text.startswith("# ") else text
    body = body.replace("](../docs/", "](")  # the README's links into docs/ are links within the site here
    return "# The Python client\n" + body + "\nEvery class and method: [Client API](reference/client.md).\n"


def pipeline_options() -> str:
    """The pipelines page: every pipeline's method and options, as ``GET /v1/pipelines`` answers them."""
    lines = [
        "# Pipelines and their options",
        "",
        (
            "Generated from the pipeline registry when the site is built; a running server answers the same "
            "with `GET /v1/pipelines`. A session sets options in its `options` object at creation; an option "
            "it does not set takes the default. Units are SI, angles radians."
        ),
        "",
    ]
    for name in sorted(PIPELINES):
        pipeline = PIPELINES[name]
        lines += [f"## `{name}`", "", pipeline.description.strip(), ""]
        lines += [f"Measurement types: {', '.join(f'`{kind}`' for kind in pipeline.measurement_kinds)}.", ""]
        lines += ["| option | type | default | bounds or choices | description |", "|---|---|---|---|---|"]
        for spec in pipeline.option_specs():
            bounds = []
            if spec.minimum is not None:
                bounds.append(f"≥ {spec.minimum:g}")
            if spec.maximum is not None:
                bounds.append(f"≤ {spec.maximum:g}")
            if spec.choices is not None:
                bounds.append("one of " + ", ".join(f"`{choice}`" for choice in spec.choices))
            lines.append(
                f"| `{spec.name}` | {spec.type} | `{_cell(json.dumps(spec.default, default=str))}` | "
                f"{_cell(', '.join(bounds))} | {_cell(spec.description)} |"
            )
        lines.append("")
    return "\n".join(lines) + "\n"


def main() -> None:
    document = json.loads((ROOT / "openapi.json").read_text(encoding="utf-8"))
    pages = {
        "reference/http-api.md": http_api(document),
        "reference/cli.md": cli(),
        "reference/configuration.md": configuration(),
        "reference/pipelines.md": pipeline_options(),
        # the client's own README (what PyPI shows) is the guide page, so the two cannot drift apart
        "client.md": client_guide(),
    }
    for path, text in pages.items():
        with mkdocs_gen_files.open(path, "w") as page:
            page.write(text)
        mkdocs_gen_files.set_edit_path(path, "gen/reference.py")


main()

"""MkDocs hook: the reference pages made from the code when the site is built, so they cannot drift.

A page holds a marker where the generated part goes:

- `<!-- generated: openapi -->` (docs/rest.md): every REST operation and schema of the OpenAPI document the
  service itself builds (`create_app(Settings(...)).openapi()`, what `/openapi.json` serves);
- `<!-- generated: api PACKAGE -->` (docs/api/*.md): a mkdocstrings entry for each name of PACKAGE's
  `__all__`, under the name a user imports (`flockcal.fit`), read from the module that defines it.

tests/test_docs_site.py builds the site with these and checks what they produced.
"""

from __future__ import annotations

import atexit
import importlib
import json
import re
import shutil
import tempfile
import tomllib
from pathlib import Path

from mkdocs.plugins import event_priority

ROOT = Path(__file__).resolve().parents[2]

MARKER = re.compile(r"^<!-- generated: (\w+)(?: ([\w.]+))? -->$", re.M)


@event_priority(100)  # before mkdocstrings reads its handlers' options
def on_config(config):
    """Point mkdocstrings at the packages as they install: pyproject's package-dir puts solver/ at
    flockcal/solver and so on, which griffe (reading files, importing nothing) cannot follow on its own."""
    python = config.plugins["mkdocstrings"].config.handlers.setdefault("python", {})
    python.setdefault("paths", []).append(str(installed_layout()))
    return config


def installed_layout() -> Path:
    """A temporary folder holding `flockcal/` as it installs: links to flockcal/'s files, and each package
    folder pyproject.toml maps (`flockcal.solver` = solver/) linked in at its place."""
    dirs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    top = Path(tempfile.mkdtemp(prefix="flockcal-docs-"))
    atexit.register(shutil.rmtree, top, ignore_errors=True)
    (top / "flockcal").mkdir()
    for entry in (ROOT / dirs["flockcal"]).iterdir():
        (top / "flockcal" / entry.name).symlink_to(entry)
    for package, folder in dirs.items():
        if package != "flockcal":
            (top / package.replace(".", "/")).symlink_to(ROOT / folder)
    return top


def on_page_markdown(markdown: str, page, config, files) -> str:
    return MARKER.sub(lambda m: GENERATORS[m.group(1)](m.group(2)), markdown)


# --- the Python API ------------------------------------------------------------------------------------
def public_names(package: str) -> list[tuple[str, str]]:
    """(name, the module defining it) for each name of `package.__all__`, in the table's order."""
    pkg = importlib.import_module(package)
    out = []
    for name in pkg.__all__:
        obj = getattr(pkg, name)
        module = getattr(obj, "__module__", None) or package
        out.append((name, module))
    return out


def api_markdown(package: str) -> str:
    """One entry per public name; a name the top-level `flockcal` also exports is documented there once and
    linked from here (autorefs finds it by the defining module's path)."""
    top = set(public_names("flockcal")) if package != "flockcal" else set()
    entries, elsewhere = [], []
    for name, module in public_names(package):
        if (name, module) in top:
            elsewhere.append(f"- `{package}.{name}` is [`flockcal.{name}`][{module}.{name}].")
            continue
        entries.append(f"::: {module}.{name}\n"
                       f"    options:\n"
                       f"      heading: \"{package}.{name}\"\n"
                       f"      toc_label: \"{name}\"\n")
    if elsewhere:
        entries.insert(0, "\n".join(elsewhere) + "\n")
    return "\n".join(entries)


# --- the REST API, from the service's own OpenAPI document ---------------------------------------------
def openapi_document() -> dict:
    """The document a service started with an admin token serves at /openapi.json (the token shows the
    security scheme; the sensor names are the built-in simulator's)."""
    from flockcal.server import Settings, create_app

    with tempfile.TemporaryDirectory() as data_dir:
        return create_app(Settings(data_dir=data_dir, token="docs-build-token")).openapi()


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def schema_type(schema: dict) -> str:
    """A JSON schema in a few words: `Session`, `string`, `array of Hint`, `object of string`, `… or null`."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[`{name}`](#{name.lower()})"
    if "anyOf" in schema or "oneOf" in schema:
        parts = [schema_type(s) for s in schema.get("anyOf", schema.get("oneOf"))]
        return " or ".join(dict.fromkeys(parts))
    if "enum" in schema:
        return " \\| ".join(f"`{json.dumps(v)}`" for v in schema["enum"])
    if "const" in schema:
        return f"`{json.dumps(schema['const'])}`"
    kind = schema.get("type", "any")
    if kind == "array":
        return f"array of {schema_type(schema.get('items', {}))}"
    if kind == "object" and isinstance(schema.get("additionalProperties"), dict):
        return f"object of {schema_type(schema['additionalProperties'])}"
    return str(kind)


def _limits(schema: dict) -> str:
    bits = []
    for s in [schema, *schema.get("anyOf", [])]:
        for key, word in (("minimum", "≥"), ("maximum", "≤"), ("minLength", "length ≥"),
                          ("maxLength", "length ≤")):
            if key in s:
                bits.append(f"{word} {s[key]}")
    if "default" in schema:
        bits.append(f"default `{json.dumps(schema['default'])}`")
    return "; ".join(bits)


def _operation(method: str, path: str, op: dict) -> list[str]:
    lines = [f"### {method.upper()} `{path}`", "", f"**{_cell(op.get('summary', ''))}**", ""]
    if op.get("description"):
        lines += [op["description"].strip(), ""]
    params = op.get("parameters", [])
    if params:
        lines += ["| parameter | in | type | meaning |", "|---|---|---|---|"]
        for p in params:
            schema = p.get("schema", {})
            extra = _limits(schema)
            meaning = _cell(p.get("description", schema.get("description", "")))
            lines.append(f"| `{p['name']}`{'' if p.get('required') else ' (optional)'} | {p['in']} | "
                         f"{schema_type(schema)} | {'; '.join(x for x in (meaning, extra) if x)} |")
        lines.append("")
    body = op.get("requestBody")
    if body:
        kinds = ", ".join(f"{schema_type(c.get('schema', {}))} (`{t}`)" for t, c in body["content"].items())
        lines += [f"Request body: {kinds}.", ""]
    ok = {k: v for k, v in op.get("responses", {}).items() if k.startswith("2")}
    errors = sorted(k for k in op.get("responses", {}) if not k.startswith("2"))
    for status, resp in ok.items():
        lines.append(f"Answer: {status}, {_response(resp)}.")
    if errors:
        lines.append(f"Errors: {', '.join(f'[{e}](#errors)' for e in errors)}.")
    return lines + [""]


def _response(resp: dict) -> str:
    content = resp.get("content", {})
    shapes = ", ".join(schema_type(c["schema"]) for c in content.values() if c.get("schema"))
    kinds = ", ".join(f"`{t}`" for t, c in content.items() if not c.get("schema"))
    what = " ".join(x for x in (shapes, kinds) if x) or "no body"
    headers = ", ".join(f"`{h}`" for h in resp.get("headers", {}))
    return f"{what}{'; header ' + headers if headers else ''}"


def _errors(doc: dict) -> list[str]:
    """Each error status once: the service answers every one of them the same way on every operation."""
    seen: dict[str, dict] = {}
    for ops in doc["paths"].values():
        for op in ops.values():
            for status, resp in op.get("responses", {}).items():
                if not status.startswith("2"):
                    if len(resp.get("description", "")) > len(seen.get(status, {}).get("description", "")):
                        seen[status] = resp
    lines = ["## Errors", "",
             "Every error answers with an [`ErrorReply`](#errorreply) (`detail`: what went wrong and what to do; "
             "`error`: a code). Each operation below lists the statuses it can answer.", "",
             "| status | meaning | headers |", "|---|---|---|"]
    for status in sorted(seen):
        resp = seen[status]
        headers = ", ".join(f"`{h}`" for h in resp.get("headers", {}))
        lines.append(f"| {status} | {_cell(resp.get('description', ''))} | {headers} |")
    return lines + [""]


def _schema(name: str, schema: dict) -> list[str]:
    lines = [f"### {name}", ""]
    if schema.get("description"):
        lines += [_cell(schema["description"]), ""]
    props = schema.get("properties", {})
    if props:
        required = set(schema.get("required", []))
        lines += ["| field | type | meaning |", "|---|---|---|"]
        for field, sub in props.items():
            extra = _limits(sub)
            meaning = _cell(sub.get("description", ""))
            lines.append(f"| `{field}`{'' if field in required else ' (optional)'} | {schema_type(sub)} | "
                         f"{'; '.join(x for x in (meaning, extra) if x)} |")
        lines.append("")
    return lines


def openapi_markdown(_arg: str | None = None) -> str:
    doc = openapi_document()
    lines = _errors(doc)
    by_tag: dict[str, list] = {}
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            by_tag.setdefault((op.get("tags") or ["other"])[0], []).append((method, path, op))
    for tag, ops in by_tag.items():
        lines += [f"## {tag.capitalize()}", ""]
        for method, path, op in ops:
            lines += _operation(method, path, op)
    schemes = doc.get("components", {}).get("securitySchemes", {})
    if schemes:
        lines += ["## Authentication", ""]
        lines += [f"- `{name}`: {s.get('type')} {s.get('scheme', '')}. {_cell(s.get('description', ''))}"
                  for name, s in schemes.items()]
        lines.append("")
    lines += ["## Schemas", ""]
    for name, schema in doc.get("components", {}).get("schemas", {}).items():
        lines += _schema(name, schema)
    return "\n".join(lines)


GENERATORS = {"api": api_markdown, "openapi": openapi_markdown}

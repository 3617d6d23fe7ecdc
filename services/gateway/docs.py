"""The API reference page at /docs, rendered on the server from the OpenAPI document: plain HTML, styled by
/static/style.css, no JavaScript and nothing from a CDN."""

from __future__ import annotations

import json
from html import escape
from typing import Any


def _schema_name(schema: dict[str, Any]) -> str:
    ref = schema.get("$ref", "")
    if ref:
        return ref.rsplit("/", 1)[-1]
    if "anyOf" in schema:
        return " | ".join(_schema_name(s) for s in schema["anyOf"])
    return str(schema.get("type", "object"))


def docs_page(spec: dict[str, Any]) -> str:
    info = spec.get("info", {})
    out = [
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>{escape(info.get('title', 'API'))} reference</title>",
        "<link rel='stylesheet' href='/static/style.css'></head><body class='docs'><main>",
        f"<h1>{escape(info.get('title', 'API'))} {escape(str(info.get('version', '')))}</h1>",
        f"<p>{escape(info.get('description', ''))}</p>",
        "<p>Machine-readable: <a href='/api/v1/openapi.json'>openapi.json</a>.</p>",
    ]
    for path, ops in spec.get("paths", {}).items():
        for method, op in ops.items():
            out.append(f"<section><h2><code>{escape(method.upper())} {escape(path)}</code></h2>")
            out.append(f"<p><strong>{escape(op.get('summary', ''))}</strong></p>")
            if op.get("description"):
                out.append(f"<p>{escape(op['description'])}</p>")
            params = op.get("parameters", [])
            if params:
                out.append("<ul>")
                for p in params:
                    out.append(f"<li><code>{escape(p.get('name', ''))}</code> ({escape(p.get('in', ''))}"
                               f"{', required' if p.get('required') else ''}): "
                               f"{escape(p.get('description', _schema_name(p.get('schema', {}))))}</li>")
                out.append("</ul>")
            body = op.get("requestBody", {}).get("content", {}).get("application/json", {}).get("schema")
            if body:
                out.append(f"<p>Body: <code>{escape(_schema_name(body))}</code> (JSON)</p>")
            codes = ", ".join(f"{escape(str(c))} {escape(r.get('description', ''))}"
                              for c, r in op.get("responses", {}).items())
            out.append(f"<p>Responses: {codes}</p></section>")
    schemas = spec.get("components", {}).get("schemas", {})
    if schemas:
        out.append("<h2>Schemas</h2>")
        for name, schema in schemas.items():
            out.append(f"<details><summary><code>{escape(name)}</code></summary>"
                       f"<pre>{escape(json.dumps(schema, indent=2))}</pre></details>")
    out.append("</main></body></html>")
    return "".join(out)

"""MCP server: agents drive aermani tasks through the gateway."""

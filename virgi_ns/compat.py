"""Work-arounds, applied on import, for nerfstudio 1.1.5 on today's torch (filled by issue 2)."""

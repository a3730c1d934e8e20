"""Report pages and figures of a fit, discovery, frequency fit or experiment design (matplotlib,
the `report` extra): `build_report`, `render_html`, `write_report` and `report_public` (the HTTP
answer) live in report/page.py, one module per kind of figure beside it."""
from greyfit.service.report.page import (
    Figure,
    Report,
    ReportDependencyMissing,
    build_report,
    render_html,
    report_public,
    write_report,
)

__all__ = ["Figure", "Report", "ReportDependencyMissing", "build_report", "render_html", "report_public",
           "write_report"]

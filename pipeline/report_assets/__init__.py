"""The session report's page: report.html (template), report.css, report.js (read by pipeline.report)."""

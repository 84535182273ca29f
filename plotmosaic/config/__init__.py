"""Every settings model: pydantic sections with bounds and a description each; they import nothing else of the project."""

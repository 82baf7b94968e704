"""Benchmarks, studies and diagnostics of spindle-chtc (outside the product)."""

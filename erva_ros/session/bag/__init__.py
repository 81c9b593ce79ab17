"""Bags: `erva bag record`, reports, offline bags, replay's re-evaluation, controls."""

"""rvt2cli.train"""

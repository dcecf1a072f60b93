"""uwbimu.cli"""

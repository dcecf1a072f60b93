"""uwbimu.design"""

"""uwbimu.eval"""

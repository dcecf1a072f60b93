"""uwbimu.sim"""

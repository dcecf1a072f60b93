"""uwbimu.io"""

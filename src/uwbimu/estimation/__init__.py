"""uwbimu.estimation"""

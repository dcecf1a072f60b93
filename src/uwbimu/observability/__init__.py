"""uwbimu.observability"""

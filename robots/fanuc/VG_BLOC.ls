/PROG  VG_BLOC
/ATTR
OWNER		= MNEDITOR;
COMMENT		= "vgripd belt locate";
PROG_SIZE	= 0;
CREATE		= DATE 26-11-29  TIME 12:00:00;
MODIFIED	= DATE 26-11-29  TIME 12:00:00;
FILE_NAME	= ;
VERSION		= 0;
LINE_COUNT	= 12;
MEMORY_SIZE	= 0;
PROTECT		= READ_WRITE;
TCD:  STACK_SIZE	= 0,
      TASK_PRIORITY	= 50,
      TIME_SLICE	= 0,
      BUSY_LAMP_OFF	= 0,
      ABORT_REQUEST	= 0,
      PAUSE_REQUEST	= 0;
DEFAULT_GROUP	= 1,*,*,*,*;
CONTROL_CODE	= 00000000 00000000;
/MN
   1:  !vgripd: CALL VG_BLOC(recipe,count) ;
   2:  !count latched at the image ;
   3:  CALL VGRIPD(AR[1],4,AR[2]) ;
   4:  IF (R[50]<>1 AND R[50]<>2),JMP LBL[99] ;
   5:  PR[50]=LPOS-LPOS ;
   6:  PR[50,1]=R[51] ;
   7:  PR[50,2]=R[52] ;
   8:  PR[50,3]=R[53] ;
   9:  PR[50,4]=R[54] ;
  10:  PR[50,5]=R[55] ;
  11:  PR[50,6]=R[56] ;
  12:  LBL[99] ;
/POS
/END
